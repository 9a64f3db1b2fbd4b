#include "worker/jobs/job_service.h"

#include <fmt/format.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <random>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_header.h"
#include "worker/jobs/job_ids.h"
#include "worker/jobs/job_service_internal.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/volume_job.h"
#include "worker/pu/pu_tiles.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {
namespace {

// The memory this process may use: the machine's, or its container's limit where that is less
// (cgroup v2); 0 when unknown (no limit then).
int64_t PhysicalMemoryBytes() {
  const long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGESIZE);
  int64_t bytes = pages > 0 && page > 0 ? static_cast<int64_t>(pages) * page : 0;
  std::ifstream cgroup("/sys/fs/cgroup/memory.max");
  int64_t limit = 0;
  if (cgroup >> limit && limit > 0) bytes = bytes > 0 ? std::min(bytes, limit) : limit;  // "max" reads as none.
  return bytes;
}

// A runner name unique to this start: a restarted service must not renew the leases of the
// jobs its previous life held.
std::string RunnerName(std::string name) {
  if (name.empty()) {
    char host[256] = {};
    name = gethostname(host, sizeof(host) - 1) == 0 && host[0] != '\0' ? host : "lsqsurfd";
  }
  return fmt::format("{}/{:08x}", name, static_cast<uint32_t>(std::random_device{}()));
}

}  // namespace

const std::map<std::string, std::string>& UploadFiles() {
  static const auto* files = new std::map<std::string, std::string>{
      {kInputUpload, "input.drc"}, {kVelocityUpload, "velocity.vtk"}, {kCellsUpload, "cells.lqc"}};
  return *files;
}

std::string UploadBlob(const std::string& slot) {
  if (const int64_t part = InputPartOf(slot); part > 0) return core::StrCat(slot, ".drc");
  return UploadFiles().at(slot);
}

int64_t SpecBytes(const JobSpec& spec) {
  const auto encoded =
      static_cast<int64_t>(spec.method.size() + spec.params.Encode().size() + spec.preview.view.Encode().size());
  return std::max<int64_t>(0, encoded - kFreeSpecBytes);
}

std::string InputPartSlot(int64_t part) { return part == 0 ? kInputUpload : core::StrCat(kInputUpload, ".", part); }

int64_t InputPartOf(std::string_view slot) {
  const std::string_view input = kInputUpload;
  if (slot == input) return 0;
  if (!slot.starts_with(input) || slot.size() < input.size() + 2 || slot[input.size()] != '.') return -1;
  const std::string_view digits = slot.substr(input.size() + 1);
  // Canonical numbers only: "input.01" would be a second name for part 1.
  if (digits.size() > 6 || digits[0] == '0') return -1;
  int64_t part = 0;
  for (const char c : digits) {
    if (c < '0' || c > '9') return -1;
    part = 10 * part + (c - '0');
  }
  return part < kMaxInputParts ? part : -1;
}

std::string MeshPartArtifact(int64_t part) { return fmt::format("mesh-part-{:05d}.lqm", part); }

int64_t MeshPartOf(std::string_view name) {
  constexpr std::string_view kPrefix = "mesh-part-", kSuffix = ".lqm";
  if (!name.starts_with(kPrefix) || !name.ends_with(kSuffix)) return -1;
  const std::string_view digits = name.substr(kPrefix.size(), name.size() - kPrefix.size() - kSuffix.size());
  int64_t part = 0;
  if (digits.size() < 5 || digits.size() > 12) return -1;
  for (const char c : digits) {
    if (c < '0' || c > '9') return -1;
    part = 10 * part + (c - '0');
  }
  return MeshPartArtifact(part) == name ? part : -1;
}

std::vector<std::string_view> InputParts(const Uploads& uploads) {
  std::vector<std::string_view> parts;
  for (int64_t part = 0; part < kMaxInputParts; ++part) {
    auto it = uploads.find(InputPartSlot(part));
    if (it == uploads.end()) break;
    parts.push_back(it->second);
  }
  return parts;
}

std::optional<uint64_t> DeclaredPoints(std::string_view head) {
  auto claim = io::ReadDracoClaim(head);
  if (!claim.ok()) return std::nullopt;
  return claim->points;
}

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

void RecoverStoppedRun(JobRecord& r, int max_attempts) {
  if (r.cancel_requested) {
    r.state = JobState::kCancelled;
    r.error = "cancelled by request (its server stopped while it ran)";
  } else if (r.attempts - r.interruptions >= max_attempts) {
    r.state = JobState::kFailed;
    r.error = core::StrCat("the server stopped while this job was running, ", r.attempts - r.interruptions,
                           " times; giving up (the input may crash the engine)");
  } else {
    r.state = JobState::kQueued;
  }
  r.stage.clear();
  r.progress = 0;
  r.results.clear();  // Parts a run published (MeshPartArtifact); the next run publishes them again.
  r.cancel_requested = false;
  r.updated_ms = NowMs();
}

JobService::JobService(JobServiceOptions options)
    : options_(std::move(options)),
      runner_(RunnerName(options_.name)),
      renderer_(std::make_unique<render::SharedRenderer>()),
      render_slots_(options_.max_renders),
      volume_pictures_(std::make_unique<VolumePictures>(options_.max_render_bytes)) {
  if (options_.max_job_memory < 0) options_.max_job_memory = PhysicalMemoryBytes() / 4 * 3;
}

absl::StatusOr<std::unique_ptr<JobService>> JobService::Open(const JobServiceOptions& options) {
  if (options.data_dir.empty()) return absl::InvalidArgumentError("a data directory is required");
  if (options.workers < 1 || options.max_queue < 1 || options.max_renders < 1) {
    return absl::InvalidArgumentError("workers, max_queue and max_renders must be at least 1");
  }
  if (options.lease < std::chrono::milliseconds(100) || options.poll < std::chrono::milliseconds(1)) {
    return absl::InvalidArgumentError("the lease must be at least 100 ms and the poll interval at least 1 ms");
  }
  std::error_code ec;
  std::filesystem::create_directories(options.data_dir, ec);
  if (ec) {
    return absl::UnavailableError(core::StrCat("cannot create data directory ", options.data_dir, ": ", ec.message()));
  }
  std::unique_ptr<JobService> service(new JobService(options));
  if (options.blobs != nullptr) {
    service->blobs_ = options.blobs;
  } else {
    auto blobs = LocalDirBlobStore::Open((std::filesystem::path(options.data_dir) / "jobs").string());
    if (!blobs.ok()) return blobs.status();
    service->blobs_ = *std::move(blobs);
  }
  if (options.store != nullptr) {
    service->store_ = options.store;
  } else {
    auto store = SqliteJobStore::Open((std::filesystem::path(options.data_dir) / "jobs.db").string());
    if (!store.ok()) return store.status();
    service->store_ = *std::move(store);
  }
  // In a store of its own every running job was this service's before it stopped; in a shared
  // one only those whose lease lapsed are known to be orphans (the sync thread goes on looking).
  LSQSURF_RETURN_IF_ERROR(service->RecoverLapsed(!service->store_->shared()));
  auto all = service->store_->ChangesSince(0);
  if (!all.ok()) return all.status();
  for (JobRecord& r : all->changed) service->Adopt(std::move(r));
  service->synced_seq_ = all->seq;
  const bool shared = service->store_->shared();
  if (!shared) service->RemoveOrphanedBlobs();
  // Large temporary files (a tiled build's points) stay beside the data, not in a temporary
  // directory that may be memory; those of a crashed run go now.
  service->scratch_dir_ = (std::filesystem::path(options.data_dir) / "scratch").string();
  std::filesystem::create_directories(service->scratch_dir_, ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot create ", service->scratch_dir_, ": ", ec.message()));
  auto swept = pu::SweepAbandonedScratch(service->scratch_dir_);
  if (!swept.ok()) return swept.status();
  if (*swept > 0) spdlog::info("removed the scratch files of {} runs that ended in a crash", *swept);
  const int64_t job_memory = service->options_.max_job_memory;
  spdlog::info("job service {}: {} jobs on record, {} queued, {} workers, {}, data in {}{}", service->runner_,
               service->jobs_.size(), service->QueuedJobs(), options.workers,
               job_memory > 0 ? core::StrCat("at most ", MiB(job_memory), " MiB a job") : "no memory limit per job",
               options.data_dir, shared ? ", store shared with other servers" : "");
  for (int i = 0; i < options.workers; ++i) service->workers_.emplace_back([s = service.get()] { s->WorkerLoop(); });
  if (shared) service->sync_thread_ = std::thread([s = service.get()] { s->SyncLoop(); });
  if (options.retain.count() > 0 || options.max_store_bytes > 0) {
    service->sweep_thread_ = std::thread([s = service.get()] {
      std::unique_lock lock(s->mutex_);
      while (!s->sweep_wake_.wait_for(lock, s->options_.sweep_interval, [s] { return s->shutting_down_; })) {
        lock.unlock();
        s->SweepFinished(NowMs());
        lock.lock();
      }
    });
  }
  return service;
}

JobService::~JobService() { Shutdown(); }

const JobKind* JobService::KindOf(const std::string& method) const {
  if (auto it = options_.kind_overrides.find(method); it != options_.kind_overrides.end()) return it->second;
  const MethodEntry* m = FindMethod(method);
  return m ? m->kind : nullptr;
}

std::shared_ptr<JobService::Entry> JobService::Adopt(JobRecord record) {
  std::shared_ptr<Entry>& entry = jobs_[record.id];
  if (entry == nullptr) entry = std::make_shared<Entry>();
  if (entry->held || (entry->record.seq >= record.seq && !entry->record.id.empty())) return entry;
  record.version = entry->record.version + 1;
  entry->record = std::move(record);
  // A job another service took (or that ended) no longer needs the input decoded here.
  if (entry->record.state != JobState::kQueued) ReleaseDecoded(entry->record.id);
  return entry;
}

std::shared_ptr<JobService::Entry> JobService::Find(const std::string& id) const {
  {
    std::lock_guard lock(mutex_);
    if (auto it = jobs_.find(id); it != jobs_.end()) return it->second;
  }
  // Another service may have accepted it a moment ago.
  if (!store_->shared()) return nullptr;
  auto stored = store_->Get(id);
  if (!stored.ok()) return nullptr;
  std::lock_guard lock(mutex_);
  return const_cast<JobService*>(this)->Adopt(*std::move(stored));
}

absl::StatusOr<JobRecord> JobService::Get(const std::string& id) const {
  std::shared_ptr<Entry> entry = Find(id);
  if (entry == nullptr) return NoSuchJob(id);
  std::lock_guard lock(mutex_);
  return entry->record;
}

absl::StatusOr<JobRecord> JobService::GetFor(const Submitter& who, const std::string& id) const {
  auto record = Get(id);
  if (record.ok() && !MayView(who, *record)) return NoSuchJob(id);
  return record;
}

std::vector<JobRecord> JobService::List() const {
  std::lock_guard lock(mutex_);
  std::vector<JobRecord> out;
  for (const auto& [id, e] : jobs_) out.push_back(e->record);
  std::sort(out.begin(), out.end(), [](const JobRecord& a, const JobRecord& b) {
    return a.created_ms != b.created_ms ? a.created_ms > b.created_ms : a.id > b.id;
  });
  return out;
}

void JobService::Update(const std::shared_ptr<Entry>& entry, const std::function<void(JobRecord&)>& change,
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

int64_t JobService::Persist(const std::shared_ptr<Entry>& entry, const JobRecord& record) {
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

absl::StatusOr<JobRecord> JobService::Cancel(const std::string& id) {
  auto cancelled = store_->Cancel(id, "cancelled by request before it started");
  if (!cancelled.ok()) return cancelled.status();
  JobRecord r;
  {
    std::lock_guard lock(mutex_);
    std::shared_ptr<Entry> entry = Adopt(*cancelled);
    if (entry->held) entry->cancel_requested = true;
    r = entry->record;
  }
  NotifyChanged();
  spdlog::info(
      "[job {}] {}", id,
      cancelled->state == JobState::kCancelled ? "cancelled while queued" : "cancellation requested while running");
  return r;
}

absl::Status JobService::Delete(const std::string& id) {
  LSQSURF_RETURN_IF_ERROR(store_->Remove(id));
  {
    std::lock_guard lock(mutex_);
    if (auto it = jobs_.find(id); it != jobs_.end()) {
      ReleaseDecoded(id);
      jobs_.erase(it);
    }
  }
  if (absl::Status s = blobs_->RemoveJob(id); !s.ok()) spdlog::error("[job {}] {}", id, s.ToString());
  NotifyChanged();
  spdlog::info("[job {}] deleted", id);
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<BlobReader>> JobService::OpenResult(const std::string& id,
                                                                   const std::string& name) const {
  auto r = Get(id);
  if (!r.ok()) return r.status();
  // A running job's published parts are there already (each stored whole before it is listed).
  const bool published = r->state == JobState::kRunning && MeshPartOf(name) >= 0;
  if (r->state != JobState::kSucceeded && !published) {
    return absl::FailedPreconditionError(core::StrCat("job ", id, " is ", JobStateName(r->state),
                                                      "; results exist only for succeeded jobs (and the mesh parts "
                                                      "of a running one)"));
  }
  if (!name.empty() && !IsArtifactNameForm(name)) return absl::InvalidArgumentError(kNotAnArtifactName);
  const std::string artifact = name.empty() && !r->results.empty() ? r->results.front() : name;
  if (std::find(r->results.begin(), r->results.end(), artifact) == r->results.end()) {
    std::string names;
    for (const auto& n : r->results) core::StrAppend(&names, names.empty() ? "" : ", ", n);
    return absl::NotFoundError(core::StrCat("job ", id, " has no result '", artifact, "'; it has: ", names));
  }
  return blobs_->Open(id, artifact);
}

void JobService::NotifyChanged() {
  {
    std::lock_guard lock(mutex_);
    ++changes_;
  }
  changed_.notify_all();
}

uint64_t JobService::WaitForAnyChange(uint64_t seen, std::chrono::milliseconds timeout) const {
  std::unique_lock lock(mutex_);
  // A shutdown counts as a change (Shutdown notifies), once: waiting on it would not wait.
  changed_.wait_for(lock, timeout, [&] { return changes_ != seen; });
  return changes_;
}

absl::StatusOr<JobRecord> JobService::WaitForChange(const std::string& id, uint64_t seen_version,
                                                    std::chrono::milliseconds timeout) const {
  std::shared_ptr<Entry> entry = Find(id);
  if (entry == nullptr) return NoSuchJob(id);
  std::unique_lock lock(mutex_);
  changed_.wait_for(lock, timeout,
                    [&] { return entry->record.version != seen_version || shutting_down_ || !jobs_.contains(id); });
  if (!jobs_.contains(id)) return absl::NotFoundError(core::StrCat("job '", id, "' was deleted"));
  return entry->record;
}

void JobService::Shutdown() {
  {
    std::lock_guard lock(mutex_);
    if (shutting_down_ && workers_.empty() && !sync_thread_.joinable() && !sweep_thread_.joinable()) return;
    shutting_down_ = true;
    for (auto& [id, e] : jobs_) {
      if (e->held) e->interrupted = true;
    }
  }
  work_available_.notify_all();
  NotifyChanged();
  sweep_wake_.notify_all();
  if (sweep_thread_.joinable()) sweep_thread_.join();
  for (auto& t : workers_) t.join();
  workers_.clear();
  // The leases are renewed until the interrupted jobs are back in the queue.
  sync_stop_ = true;
  if (sync_thread_.joinable()) sync_thread_.join();
}

}  // namespace lsqsurf::jobs
