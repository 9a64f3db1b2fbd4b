#include <spdlog/spdlog.h>

#include <algorithm>
#include <set>

#include "worker/jobs/job_service.h"
#include "worker/jobs/job_service_internal.h"

namespace lsqsurf::jobs {

void JobService::MarkLost(Entry& entry, const std::string& id) {
  if (!entry.lost.exchange(true)) spdlog::warn("[job {}] lease lost; this run stops", id);
}

absl::Status JobService::RecoverLapsed(bool every_running) {
  auto recovered =
      store_->RecoverLapsed(every_running, [this](JobRecord& r) { RecoverStoppedRun(r, options_.max_attempts); });
  if (!recovered.ok()) return recovered.status();
  for (const JobRecord& r : *recovered) {
    spdlog::warn("[job {}] its server ({}) stopped while it ran: {}", r.id, r.runner,
                 r.state == JobState::kQueued ? "queued again" : r.error);
  }
  return absl::OkStatus();
}

void JobService::SyncChanges() {
  auto changes = store_->ChangesSince(synced_seq_);
  // Logged when the store goes away and when it comes back, not at every poll.
  if (store_reachable_.exchange(changes.ok()) != changes.ok()) {
    if (changes.ok()) {
      spdlog::info("the job store answers again");
    } else {
      spdlog::warn("cannot reach the job store: {}", changes.status().ToString());
    }
  }
  if (!changes.ok()) return;
  bool queued = false;
  {
    std::lock_guard lock(mutex_);
    for (JobRecord& r : changes->changed) {
      const bool cancel = r.cancel_requested;
      // Queued again, someone else's, or ended while this run goes on: changes made by others
      // since this server claimed it (not this run's own writes, nor older states arriving late).
      auto known = jobs_.find(r.id);
      const bool newer = known == jobs_.end() || r.seq > known->second->record.seq;
      const bool ended_elsewhere =
          r.state != JobState::kRunning && known != jobs_.end() && known->second->record.state == JobState::kRunning;
      const bool taken = newer && (r.runner != runner_ || r.state == JobState::kQueued || ended_elsewhere);
      const int64_t seq = r.seq;
      std::shared_ptr<Entry> entry = Adopt(std::move(r));
      if (entry->held) {
        // The runner learns of a cancellation asked of another service, and of a lease that
        // lapsed while it could not renew (the job went back to the queue or to another).
        // While its own write is under way, that write may be what arrived: the write decides.
        if (cancel) entry->cancel_requested = true;
        if (taken && entry->writes_in_flight > 0) {
          entry->seq_seen_while_writing = std::max(entry->seq_seen_while_writing, seq);
        } else if (taken && !entry->interrupted) {
          MarkLost(*entry, entry->record.id);
        }
      }
      queued = queued || entry->record.state == JobState::kQueued;
    }
    for (const std::string& id : changes->removed) {
      auto it = jobs_.find(id);
      if (it == jobs_.end()) continue;
      if (it->second->held) {
        // Its run ends by itself (its next write finds no lease); then the entry goes.
        it->second->removed_elsewhere = true;
        continue;
      }
      ReleaseDecoded(id);
      jobs_.erase(it);
    }
    synced_seq_ = changes->seq;
    if (queued) ++work_signal_;
  }
  NotifyChanged();
  if (queued) work_available_.notify_all();
}

void JobService::HoldTile(const TileTask& task, bool held) {
  std::lock_guard lock(mutex_);
  const auto same = [&](const TileTask& t) { return t.job_id == task.job_id && t.tile == task.tile; };
  std::erase_if(held_tiles_, same);
  if (held) held_tiles_.push_back(task);
}

void JobService::RenewLeases() {
  std::vector<std::string> running;
  std::vector<TileTask> tiles;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, e] : jobs_) {
      if (e->held && !e->lost) running.push_back(id);
    }
    tiles = held_tiles_;
  }
  // A tile lost here is claimed by another server; this one's part, should it still come, is
  // the same surface and is not counted as the tile's.
  if (auto renewed = store_->RenewTiles(runner_, tiles, options_.lease); !renewed.ok()) {
    spdlog::warn("cannot renew the leases of the running tiles: {}", renewed.status().ToString());
  }
  auto held = store_->Renew(runner_, running, options_.lease);
  if (!held.ok()) {
    spdlog::warn("cannot renew the leases of the running jobs: {}", held.status().ToString());
    return;
  }
  std::set<std::string> ids;
  std::lock_guard lock(mutex_);
  for (const auto& [id, cancel] : *held) {
    ids.insert(id);
    auto it = jobs_.find(id);
    if (cancel && it != jobs_.end()) it->second->cancel_requested = true;
  }
  for (const std::string& id : running) {
    auto it = jobs_.find(id);
    // Held here but not in the store any more: taken over, or finished a moment ago (its
    // final write may be under way; if it was taken, that write is refused).
    if (it != jobs_.end() && it->second->held && it->second->writes_in_flight == 0 &&
        it->second->record.state == JobState::kRunning && !ids.contains(id))
      it->second->lost = true;
  }
}

void JobService::SyncLoop() {
  using Clock = std::chrono::steady_clock;
  Clock::time_point next_renewal = Clock::now(), next_recovery = Clock::now();
  while (!sync_stop_) {
    store_->WaitForOthers(options_.poll);
    SyncChanges();
    const Clock::time_point now = Clock::now();
    if (now >= next_renewal) {
      RenewLeases();
      next_renewal = now + options_.lease / 4;
    }
    if (now >= next_recovery) {
      if (absl::Status s = RecoverLapsed(false); !s.ok()) spdlog::warn("cannot recover lapsed jobs: {}", s.ToString());
      next_recovery = now + options_.lease / 2;
    }
  }
}

}  // namespace lsqsurf::jobs
