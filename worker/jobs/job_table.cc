#include "worker/jobs/job_table.h"

#include <spdlog/spdlog.h>

#include <algorithm>

#include "worker/core/strings.h"
#include "worker/jobs/job_service_internal.h"

namespace lsqsurf::jobs {

bool DecodedInputs::Keep(const std::string& id, std::shared_ptr<DecodedInput> input, int64_t points) {
  std::lock_guard lock(mutex_);
  if (input == nullptr || points_ + points > max_points_) return false;
  held_[id] = {std::move(input), points};
  points_ += points;
  return true;
}

std::shared_ptr<DecodedInput> DecodedInputs::Take(const std::string& id) {
  std::lock_guard lock(mutex_);
  auto it = held_.find(id);
  if (it == held_.end()) return nullptr;
  points_ -= it->second.points;
  std::shared_ptr<DecodedInput> input = std::move(it->second.input);
  held_.erase(it);
  return input;
}

std::shared_ptr<JobEntry> JobTable::AdoptLocked(JobRecord record) const {
  std::shared_ptr<JobEntry>& entry = jobs_[record.id];
  if (entry == nullptr) entry = std::make_shared<JobEntry>();
  if (entry->held || (entry->record.seq >= record.seq && !entry->record.id.empty())) return entry;
  record.version = entry->record.version + 1;
  entry->record = std::move(record);
  if (IsChildJob(entry->record)) children_[entry->record.parent].insert(entry->record.id);
  // A job another service took (or that ended) no longer needs the input decoded here.
  if (entry->record.state != JobState::kQueued) decoded_.Take(entry->record.id);
  return entry;
}

void JobTable::EraseLocked(const std::string& id) const {
  decoded_.Take(id);
  const auto it = jobs_.find(id);
  if (it == jobs_.end()) return;
  if (const std::string& parent = it->second->record.parent; !parent.empty()) {
    if (auto siblings = children_.find(parent); siblings != children_.end()) {
      siblings->second.erase(id);
      if (siblings->second.empty()) children_.erase(siblings);
    }
  }
  jobs_.erase(it);
}

std::shared_ptr<JobEntry> JobTable::Find(const std::string& id) const {
  {
    std::lock_guard lock(mutex_);
    if (auto it = jobs_.find(id); it != jobs_.end()) return it->second;
  }
  // Another service may have accepted it a moment ago.
  if (!store_->shared()) return nullptr;
  auto stored = store_->Get(id);
  if (!stored.ok()) return nullptr;
  std::lock_guard lock(mutex_);
  return AdoptLocked(*std::move(stored));
}

std::vector<JobRecord> JobTable::Children(const std::string& parent, const std::function<bool(const JobRecord&)>& keep,
                                          size_t at_most) const {
  std::lock_guard lock(mutex_);
  std::vector<JobRecord> out;
  const auto ids = children_.find(parent);
  if (ids == children_.end()) return out;
  for (const std::string& id : ids->second) {
    if (out.size() >= at_most) break;
    const JobRecord& r = jobs_.at(id)->record;
    if (keep == nullptr || keep(r)) out.push_back(r);
  }
  return out;
}

absl::StatusOr<JobRecord> JobTable::Get(const std::string& id) const {
  std::shared_ptr<JobEntry> entry = Find(id);
  if (entry == nullptr) return NoSuchJob(id);
  return Snapshot(*entry);
}

JobRecord JobTable::Snapshot(const JobEntry& entry) const {
  std::lock_guard lock(mutex_);
  return entry.record;
}

std::vector<JobRecord> JobTable::List() const {
  std::lock_guard lock(mutex_);
  std::vector<JobRecord> out;
  for (const auto& [id, e] : jobs_) {
    if (!IsChildJob(e->record)) out.push_back(e->record);  // A tile's job is its build's business.
  }
  std::sort(out.begin(), out.end(), [](const JobRecord& a, const JobRecord& b) {
    return a.created_ms != b.created_ms ? a.created_ms > b.created_ms : a.id > b.id;
  });
  return out;
}

void JobTable::Update(const std::shared_ptr<JobEntry>& entry, const std::function<void(JobRecord&)>& change,
                      bool persist) {
  if (!persist) {
    {
      std::lock_guard lock(mutex_);
      change(entry->record);
      entry->record.updated_ms = NowMs();
      ++entry->record.version;
    }
    NotifyChanged();
    return;
  }
  // A stored change shows here only once the store has it: whoever sees it (a watcher that then
  // cancels or deletes the job, through this server or another) finds the store agreeing. The
  // held job's record changes only through here meanwhile (progress is reported under the
  // context's lock, and the run ends after its last report).
  JobRecord next;
  {
    std::lock_guard lock(mutex_);
    next = entry->record;
    ++entry->writes_in_flight;
  }
  change(next);
  next.updated_ms = NowMs();
  const int64_t seq = Persist(entry, next);
  {
    std::lock_guard lock(mutex_);
    // A change seen during the write that is newer than the write itself (or, when the write
    // failed, than what this run had stored before) was another service's.
    if (entry->seq_seen_while_writing > (seq != 0 ? seq : entry->record.seq)) MarkLost(*entry, next.id);
    next.version = entry->record.version + 1;
    next.seq = std::max(entry->record.seq, seq);
    entry->record = std::move(next);
    if (--entry->writes_in_flight == 0) entry->seq_seen_while_writing = 0;
  }
  NotifyChanged();
}

int64_t JobTable::Persist(const std::shared_ptr<JobEntry>& entry, const JobRecord& record) {
  absl::StatusOr<int64_t> seq;
  {
    std::lock_guard store_lock(store_mutex_);
    seq = store_->WriteHeld(record);
  }
  if (seq.ok()) return *seq;
  if (seq.status().code() == absl::StatusCode::kAborted) {
    // Its lease lapsed (this service stalled or lost the store): another service runs it now.
    MarkLost(*entry, record.id);
  } else {
    spdlog::error("[job {}] cannot store its state: {}", record.id, seq.status().ToString());
  }
  return 0;
}

std::shared_ptr<JobEntry> JobTable::Hold(JobRecord claimed) {
  std::shared_ptr<JobEntry> entry;
  {
    std::lock_guard lock(mutex_);
    entry = AdoptLocked(std::move(claimed));
    entry->held = true;
    // A cancellation that reached the store between the claim and this line is in the record
    // kept (AdoptLocked keeps the newer one); the run must see it, as no one will tell it again.
    entry->cancel_requested = entry->record.cancel_requested;
    entry->lost = false;
    // A shutdown that began during the claim has marked the held jobs already: this one goes
    // back to the queue at once instead of running until it ends.
    entry->interrupted = shutting_down_;
  }
  NotifyChanged();
  return entry;
}

void JobTable::Release(const std::shared_ptr<JobEntry>& entry) {
  std::string id;
  {
    std::lock_guard lock(mutex_);
    entry->held = false;
    if (!entry->lost && !entry->removed_elsewhere) return;
    entry->record.seq = 0;  // Whatever the store holds now replaces this run's view.
    id = entry->record.id;
  }
  auto stored = store_->Get(id);
  {
    std::lock_guard lock(mutex_);
    if (stored.ok()) {
      AdoptLocked(*std::move(stored));
    } else if (stored.status().code() == absl::StatusCode::kNotFound) {
      // Deleted elsewhere while it ran here: nothing of it stays on this server either.
      if (auto it = jobs_.find(id); it != jobs_.end() && it->second == entry) EraseLocked(id);
    }
  }
  NotifyChanged();
}

absl::StatusOr<JobRecord> JobTable::Cancel(const std::string& id) {
  auto cancelled = store_->Cancel(id, "cancelled by request before it started");
  if (!cancelled.ok()) return cancelled.status();
  JobRecord r;
  {
    std::lock_guard lock(mutex_);
    std::shared_ptr<JobEntry> entry = AdoptLocked(*cancelled);
    if (entry->held) entry->cancel_requested = true;
    r = entry->record;
  }
  NotifyChanged();
  spdlog::info(
      "[job {}] {}", id,
      cancelled->state == JobState::kCancelled ? "cancelled while queued" : "cancellation requested while running");
  return r;
}

void JobTable::MarkLost(JobEntry& entry, const std::string& id) {
  if (!entry.lost.exchange(true)) spdlog::warn("[job {}] lease lost; this run stops", id);
}

void JobTable::NotifyChanged() {
  {
    std::lock_guard lock(mutex_);
    ++changes_;
  }
  changed_.notify_all();
}

uint64_t JobTable::WaitForAnyChange(uint64_t seen, std::chrono::milliseconds timeout) const {
  std::unique_lock lock(mutex_);
  // A shutdown counts as a change (BeginShutdown notifies), once: waiting on it would not wait.
  changed_.wait_for(lock, timeout, [&] { return changes_ != seen; });
  return changes_;
}

absl::StatusOr<JobRecord> JobTable::WaitForChange(const std::string& id, uint64_t seen_version,
                                                  std::chrono::milliseconds timeout) const {
  std::shared_ptr<JobEntry> entry = Find(id);
  if (entry == nullptr) return NoSuchJob(id);
  std::unique_lock lock(mutex_);
  changed_.wait_for(lock, timeout,
                    [&] { return entry->record.version != seen_version || shutting_down_ || !jobs_.contains(id); });
  if (!jobs_.contains(id)) return absl::NotFoundError(core::StrCat("job '", id, "' was deleted"));
  return entry->record;
}

bool JobTable::BeginShutdown() {
  bool first = false;
  {
    std::lock_guard lock(mutex_);
    first = !shutting_down_;
    shutting_down_ = true;
    for (auto& [id, e] : jobs_) {
      if (e->held) e->interrupted = true;
    }
  }
  NotifyChanged();
  return first;
}

bool JobTable::shutting_down() const {
  std::lock_guard lock(mutex_);
  return shutting_down_;
}

}  // namespace lsqsurf::jobs
