#include "worker/jobs/job_service.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <set>
#include <tuple>

#include "absl/cleanup/cleanup.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/job_ids.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/volume_job.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {
namespace {

int64_t MiB(int64_t bytes) { return (bytes + (int64_t{1} << 20) - 1) >> 20; }

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

// Where each upload slot is kept in a job's folder (names kept from earlier versions).
const std::map<std::string, std::string>& UploadFiles() {
  static const auto* files = new std::map<std::string, std::string>{
      {kInputUpload, "input.drc"}, {kVelocityUpload, "velocity.vtk"}, {kCellsUpload, "cells.lqc"}};
  return *files;
}

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
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

// The new state of a job whose runner stopped while it ran: cancelled if that was asked for,
// queued again, or failed once such stops add up to `max_attempts`.
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
  r.cancel_requested = false;
  r.updated_ms = NowMs();
}

}  // namespace

// Writes a job's artifacts into the blob store, recording their names in order.
// Each write is first admitted with what all the job's artifacts would then take (quotas).
class BlobSink final : public ArtifactSink {
 public:
  using Admit = std::function<absl::Status(int64_t artifact_bytes)>;
  BlobSink(BlobStore& blobs, std::string job_id, Admit admit)
      : blobs_(blobs), job_id_(std::move(job_id)), admit_(std::move(admit)) {}
  absl::Status Write(std::string_view name, std::string_view bytes) override {
    {
      std::lock_guard lock(mutex_);
      int64_t after = static_cast<int64_t>(bytes.size());
      for (const auto& [kept, size] : sizes_) after += kept == name ? 0 : size;
      LSQSURF_RETURN_IF_ERROR(admit_(after));
    }
    LSQSURF_RETURN_IF_ERROR(blobs_.Put(job_id_, name, bytes));
    std::lock_guard lock(mutex_);
    if (std::find(names_.begin(), names_.end(), name) == names_.end()) names_.emplace_back(name);
    sizes_[std::string(name)] = static_cast<int64_t>(bytes.size());
    return absl::OkStatus();
  }
  std::vector<std::string> names() const {
    std::lock_guard lock(mutex_);
    return names_;
  }
  int64_t bytes() const {  // Of the artifacts as last written.
    std::lock_guard lock(mutex_);
    int64_t total = 0;
    for (const auto& [name, size] : sizes_) total += size;
    return total;
  }

 private:
  BlobStore& blobs_;
  std::string job_id_;
  Admit admit_;
  mutable std::mutex mutex_;
  std::vector<std::string> names_;
  std::map<std::string, int64_t> sizes_;
};

struct JobService::Entry {
  JobRecord record;   // Guarded by mutex_.
  bool held = false;  // This service runs the job; guarded by mutex_.
  std::atomic<bool> cancel_requested{false};
  std::atomic<bool> interrupted{false};  // Shutdown: re-queue rather than cancel.
  std::atomic<bool> lost{false};         // The lease lapsed: another service may run it now.
  // This run's writes to the store under way, and the newest change that arrived meanwhile
  // looking like another service's (it may be one of them, stored but not yet recorded here);
  // guarded by mutex_.
  int writes_in_flight = 0;
  int64_t seq_seen_while_writing = 0;
  bool removed_elsewhere = false;  // Deleted through another service while held; guarded by mutex_.
};

// Progress of a running job, published to watchers at most every half percent, and written to
// a shared store (for the other services' watchers) at most twice a second.
class JobService::Context : public core::JobContext {
 public:
  Context(JobService& service, std::shared_ptr<Entry> entry, std::string method)
      : service_(service), entry_(std::move(entry)), method_(std::move(method)) {}
  void ReportProgress(std::string_view stage, double fraction) override {
    std::lock_guard lock(mutex_);
    if (stage == last_stage_ && std::abs(fraction - last_fraction_) < 0.005) return;
    const auto now = std::chrono::steady_clock::now();
    if (stage != last_stage_) EndStage(now);
    last_stage_.assign(stage);
    last_fraction_ = fraction;
    const bool persist = service_.store_->shared() && now - last_persisted_ >= std::chrono::milliseconds(500);
    if (persist) last_persisted_ = now;
    service_.Update(
        entry_,
        [&](JobRecord& r) {
          r.stage = last_stage_;
          r.progress = std::clamp(fraction, 0.0, 1.0);
        },
        persist);
  }
  bool IsCancelled() const override {
    return entry_->cancel_requested.load() || entry_->interrupted.load() || entry_->lost.load();
  }
  // Reports the stage in progress as ended (at the end of the run).
  void Finish() {
    std::lock_guard lock(mutex_);
    EndStage(std::chrono::steady_clock::now());
    last_stage_.clear();
  }

 private:
  void EndStage(std::chrono::steady_clock::time_point now) {  // mutex_ held.
    if (!last_stage_.empty() && service_.options_.events != nullptr) {
      service_.options_.events->StageEnded(method_, last_stage_,
                                           std::chrono::duration<double>(now - stage_start_).count());
    }
    stage_start_ = now;
  }

  JobService& service_;
  std::shared_ptr<Entry> entry_;
  const std::string method_;
  std::mutex mutex_;
  std::string last_stage_;
  double last_fraction_ = -1;
  std::chrono::steady_clock::time_point last_persisted_{};
  std::chrono::steady_clock::time_point stage_start_ = std::chrono::steady_clock::now();
};

JobService::JobService(JobServiceOptions options)
    : options_(std::move(options)),
      runner_(RunnerName(options_.name)),
      renderer_(std::make_unique<render::SharedRenderer>()) {
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

void JobService::RemoveOrphanedBlobs() {
  std::set<std::string> known;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, e] : jobs_) known.insert(id);
  }
  auto removed = blobs_->RemoveOrphans([&](const std::string& id) { return known.count(id) > 0; });
  if (!removed.ok()) {
    if (removed.status().code() != absl::StatusCode::kUnimplemented) {
      spdlog::warn("orphaned files not removed: {}", removed.status().ToString());
    }
  } else if (*removed > 0) {
    spdlog::info("removed the files of {} jobs that were never stored or whose deletion was cut short", *removed);
  }
}

const JobKind* JobService::KindOf(const std::string& method) const {
  if (auto it = options_.kind_overrides.find(method); it != options_.kind_overrides.end()) return it->second;
  const MethodEntry* m = FindMethod(method);
  return m ? m->kind : nullptr;
}

absl::StatusOr<JobRecord> JobService::Submit(const JobSpec& spec, Uploads uploads, const Submitter& submitter) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpec(spec));
  // A job that reads another's results may name only jobs its submitter may see; the run reads
  // no others (RunKind).
  for (const std::string& referenced : KindOf(spec.method)->ReferencedJobs(spec)) {
    if (!IsJobIdForm(referenced)) return absl::InvalidArgumentError(core::StrCat("a referenced ", kNotAJobId));
    LSQSURF_RETURN_IF_ERROR(GetFor(submitter, referenced).status());
  }
  if (spec.preview.enabled) {
    if (auto r = renderer_->Get(); !r.ok()) {
      return absl::UnavailableError(
          core::StrCat("this server cannot draw previews (", r.status().message(), "); submit the job without one"));
    }
  }
  const MethodEntry* method = FindMethod(spec.method);
  int64_t bytes = 0;
  for (auto it = uploads.begin(); it != uploads.end();) {
    if (it->second.empty()) {
      it = uploads.erase(it);
      continue;
    }
    const auto& accepted = method->info.uploads;
    if (std::find(accepted.begin(), accepted.end(), it->first) == accepted.end()) {
      return absl::InvalidArgumentError(core::StrCat("the ", spec.method, " method takes no '", it->first, "' upload"));
    }
    bytes += static_cast<int64_t>(it->second.size());
    ++it;
  }
  if (const int64_t limit = MaxUploadBytes(submitter); bytes > limit) {
    return absl::ResourceExhaustedError(core::StrCat(
        "the upload has ", bytes, " bytes; ",
        limit < options_.max_input_bytes ? "your quota allows" : "this server accepts", " at most ", limit));
  }
  LSQSURF_RETURN_IF_ERROR(CheckRoom(bytes + ResultReserve(bytes)));
  auto checked =
      KindOf(spec.method)
          ->CheckUploads(spec, uploads,
                         {options_.max_points, options_.min_points, options_.max_cells, options_.max_job_memory});
  if (!checked.ok()) return checked.status();
  if (const int64_t limit = options_.max_job_memory; limit > 0 && checked->memory.bytes > limit) {
    return absl::ResourceExhaustedError(core::StrCat("this job would take about ", MiB(checked->memory.bytes),
                                                     " MiB of memory, more than the ", MiB(limit),
                                                     " MiB a job may take on this server; ", checked->memory.hint));
  }
  JobRecord r;
  r.id = NewJobId();
  r.spec = spec;
  r.owner = submitter.owner;
  r.created_ms = r.updated_ms = NowMs();
  r.input_points = checked->points;
  r.input_bytes = bytes;
  // Its results are still to come: a reservation counts them until the run settles what they took.
  r.stored_bytes = bytes + ResultReserve(bytes);
  r.quota_bytes = submitter.max_stored_bytes;
  {
    std::lock_guard lock(mutex_);
    if (shutting_down_) return absl::UnavailableError("the server is shutting down");
    if (const int queued = QueuedJobs(); queued >= options_.max_queue) {
      return absl::ResourceExhaustedError(
          core::StrCat("the job queue is full (", queued, " jobs waiting); try again later"));
    }
    // A named user may fill half of the queue (rounded up), so that others still get in.
    if (!submitter.owner.empty() && 2 * QueuedJobsOf(submitter.owner) >= options_.max_queue) {
      return absl::ResourceExhaustedError(core::StrCat("you have ", QueuedJobsOf(submitter.owner),
                                                       " jobs waiting, half of this server's queue; submit more once "
                                                       "they have started"));
    }
    LSQSURF_RETURN_IF_ERROR(CheckQuota(submitter, r.stored_bytes));
    // Held against the quota until the job's entry counts itself.
    Usage& pending = pending_[submitter.owner];
    ++pending.active_jobs;
    pending.stored_bytes += r.stored_bytes;
  }
  const absl::Cleanup release_pending = [&] {
    std::lock_guard lock(mutex_);
    Usage& pending = pending_[submitter.owner];
    --pending.active_jobs;
    pending.stored_bytes -= r.stored_bytes;
    if (pending.active_jobs == 0) pending_.erase(submitter.owner);
  };
  for (const auto& [slot, data] : uploads) {
    if (absl::Status s = blobs_->Put(r.id, UploadFiles().at(slot), data); !s.ok()) {
      (void)blobs_->RemoveJob(r.id);
      return s;
    }
  }
  {
    // The decoded input waits with the job while the waiting ones hold at most max_points
    // points. It is in place before the job is stored: a worker may claim it at once.
    std::lock_guard lock(mutex_);
    if (checked->decoded != nullptr && decoded_points_ + r.input_points <= options_.max_points) {
      decoded_[r.id] = {std::move(checked->decoded), r.input_points};
      decoded_points_ += r.input_points;
    }
  }
  // Stored before it is visible: a job the caller hears of survives a crash.
  if (absl::Status s = store_->Insert(r); !s.ok()) {
    (void)blobs_->RemoveJob(r.id);
    std::lock_guard lock(mutex_);
    ReleaseDecoded(r.id);
    return s;
  }
  {
    std::lock_guard lock(mutex_);
    std::shared_ptr<Entry>& entry = jobs_[r.id];
    // A worker may have claimed the job already; its entry stays.
    if (entry == nullptr) {
      entry = std::make_shared<Entry>();
      entry->record = r;
    }
    ++work_signal_;
  }
  work_available_.notify_one();
  spdlog::info("[job {}] accepted: method {}, {} points, {} bytes", r.id, spec.method, r.input_points, r.input_bytes);
  return r;
}

int64_t JobService::MaxUploadBytes(const Submitter& submitter) const {
  return submitter.max_upload_bytes > 0 ? std::min(submitter.max_upload_bytes, options_.max_input_bytes)
                                        : options_.max_input_bytes;
}

JobService::Usage JobService::UsageOf(const std::string& owner) const {
  std::lock_guard lock(mutex_);
  return OwnerUsage(owner);
}

JobService::Usage JobService::OwnerUsage(const std::string& owner) const {
  Usage usage;
  if (auto it = pending_.find(owner); it != pending_.end()) usage = it->second;
  for (const auto& [id, e] : jobs_) {
    if (e->record.owner != owner) continue;
    usage.active_jobs += !IsTerminal(e->record.state);
    usage.stored_bytes += e->record.stored_bytes;
  }
  return usage;
}

absl::Status JobService::CheckQuota(const Submitter& submitter, int64_t job_bytes) const {
  if (submitter.max_active_jobs <= 0 && submitter.max_stored_bytes <= 0) return absl::OkStatus();
  const Usage usage = OwnerUsage(submitter.owner);
  if (submitter.max_active_jobs > 0 && usage.active_jobs >= submitter.max_active_jobs) {
    return absl::ResourceExhaustedError(core::StrCat(
        "you have ", usage.active_jobs, " jobs queued or running, your quota's limit; wait for one to end"));
  }
  if (submitter.max_stored_bytes > 0 && usage.stored_bytes + job_bytes > submitter.max_stored_bytes) {
    return absl::ResourceExhaustedError(
        core::StrCat("your jobs keep ", usage.stored_bytes, " bytes and this job needs ", job_bytes,
                     " (its upload, and a reserve for its results); your quota allows ", submitter.max_stored_bytes,
                     " in all: delete finished jobs to make room"));
  }
  return absl::OkStatus();
}

absl::Status JobService::CheckRoom(int64_t job_bytes) {
  if (options_.max_store_bytes > 0 && StoredBytes() + job_bytes > options_.max_store_bytes) {
    SweepFinished(NowMs(), job_bytes);
    if (const int64_t kept = StoredBytes(); kept + job_bytes > options_.max_store_bytes) {
      return absl::ResourceExhaustedError(core::StrCat(
          "the server's store is full: its jobs keep ", kept, " of ", options_.max_store_bytes,
          " bytes and this job needs ", job_bytes,
          " (its upload and a reserve for its results); try again once jobs have finished and been deleted"));
    }
  }
  if (const int64_t available = blobs_->AvailableBytes();
      available >= 0 && available - job_bytes < options_.min_free_bytes) {
    return absl::ResourceExhaustedError(core::StrCat("the server's disk is nearly full (", available >> 20,
                                                     " MiB free, ", options_.min_free_bytes >> 20,
                                                     " MiB kept for running jobs); try again later"));
  }
  return absl::OkStatus();
}

int64_t JobService::StoredBytes() const {
  std::lock_guard lock(mutex_);
  int64_t total = 0;
  for (const auto& [id, e] : jobs_) total += e->record.stored_bytes;
  for (const auto& [owner, usage] : pending_) total += usage.stored_bytes;
  return total;
}

int JobService::SweepFinished(int64_t now_ms, int64_t room) {
  struct Finished {
    int64_t ended_ms, seq, bytes;
    std::string id;
  };
  std::vector<Finished> finished;
  int64_t total = 0;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, e] : jobs_) {
      total += e->record.stored_bytes;
      if (IsTerminal(e->record.state)) {
        finished.push_back({e->record.updated_ms, e->record.seq, e->record.stored_bytes, id});
      }
    }
  }
  std::sort(finished.begin(), finished.end(), [](const Finished& a, const Finished& b) {
    return std::tie(a.ended_ms, a.seq) < std::tie(b.ended_ms, b.seq);  // Within a millisecond, store order.
  });
  const int64_t retain_ms = std::chrono::duration_cast<std::chrono::milliseconds>(options_.retain).count();
  int removed = 0;
  for (const Finished& f : finished) {
    const bool expired = retain_ms > 0 && now_ms - f.ended_ms > retain_ms;
    const bool over = options_.max_store_bytes > 0 && total + room > options_.max_store_bytes;
    if (!expired && !over) break;  // Oldest first: the rest are newer.
    // Another server sharing the store may have deleted it already.
    if (absl::Status s = Delete(f.id); !s.ok() && s.code() != absl::StatusCode::kNotFound) {
      spdlog::warn("[job {}] not deleted by retention: {}", f.id, s.ToString());
      continue;
    }
    total -= f.bytes;
    ++removed;
    spdlog::info("[job {}] deleted by retention ({})", f.id,
                 expired ? "older than --retain-days" : "store over --max-store-gib");
  }
  return removed;
}

int JobService::QueuedJobs() const {
  int queued = 0;
  for (const auto& [id, e] : jobs_) queued += e->record.state == JobState::kQueued;
  return queued;
}

int JobService::QueuedJobsOf(const std::string& owner) const {
  int queued = 0;
  for (const auto& [id, e] : jobs_) queued += e->record.state == JobState::kQueued && e->record.owner == owner;
  return queued;
}

absl::Status JobService::AdmitResults(const std::shared_ptr<Entry>& entry, int64_t artifact_bytes) {
  std::lock_guard lock(mutex_);
  JobRecord& r = entry->record;
  const int64_t total = r.input_bytes + artifact_bytes;
  if (r.quota_bytes > 0) {
    const int64_t others = OwnerUsage(r.owner).stored_bytes - r.stored_bytes;
    if (others + total > r.quota_bytes) {
      return absl::ResourceExhaustedError(core::StrCat("the job's results would take your jobs past your quota of ",
                                                       r.quota_bytes, " stored bytes (the others keep ", others,
                                                       "); delete finished jobs to make room"));
    }
  }
  // The reservation stands until the run settles; past it, what was written counts at once.
  r.stored_bytes = std::max(r.stored_bytes, total);
  return absl::OkStatus();
}

void JobService::MarkLost(Entry& entry, const std::string& id) {
  if (!entry.lost.exchange(true)) spdlog::warn("[job {}] lease lost; this run stops", id);
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
  if (r->state != JobState::kSucceeded) {
    return absl::FailedPreconditionError(
        core::StrCat("job ", id, " is ", JobStateName(r->state), "; results exist only for succeeded jobs"));
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

bool JobService::TakeRenderSlot(const std::string& owner) {
  std::lock_guard lock(render_mutex_);
  if (renders_ >= options_.max_renders) return false;
  if (!owner.empty()) {
    int& mine = owner_renders_[owner];
    if (mine >= (options_.max_renders + 1) / 2) {
      if (mine == 0) owner_renders_.erase(owner);
      return false;
    }
    ++mine;
  }
  ++renders_;
  return true;
}

void JobService::ReleaseRenderSlot(const std::string& owner) {
  std::lock_guard lock(render_mutex_);
  --renders_;
  if (auto it = owner_renders_.find(owner); it != owner_renders_.end() && --it->second == 0) owner_renders_.erase(it);
}

absl::StatusOr<RenderedPicture> JobService::Render(const Submitter& who, const std::string& id, const std::string& name,
                                                   const core::ParamSet& view, const core::JobContext* ctx) {
  LSQSURF_RETURN_IF_ERROR(GetFor(who, id).status());
  const auto* params = view.As<render::RenderParams>();
  if (params == nullptr) return absl::InternalError("view options of another type");
  // Checked before any file is read or a context is made.
  LSQSURF_RETURN_IF_ERROR(render::Validate(*params));
  if (!TakeRenderSlot(who.owner)) {
    return absl::ResourceExhaustedError(core::StrCat("the pictures this server draws at once (", options_.max_renders,
                                                     ", half of them per user) are being drawn; "
                                                     "try again shortly"));
  }
  const absl::Cleanup release = [&] { ReleaseRenderSlot(who.owner); };
  auto reader = OpenResult(id, name);
  if (!reader.ok()) return reader.status();
  auto read = ReadAll(**reader);
  if (!read.ok()) return read.status();
  const std::string& bytes = *read;
  if (volume::IsStoredVolumeField(bytes)) return RenderVolumeField(id, bytes, *params, ctx);
  auto geometry = io::PeekDracoGeometry(bytes);
  if (!geometry.ok()) {
    return absl::InvalidArgumentError(
        core::StrCat("artifact '", name, "' is not a Draco mesh or point set; only those can be rendered"));
  }
  auto renderer = renderer_->Get();
  if (!renderer.ok()) return renderer.status();
  render::RenderInfo info;
  absl::StatusOr<render::Image> image = absl::InvalidArgumentError("");
  if (*geometry == io::DracoGeometry::kTriangleMesh) {
    auto mesh = io::DecodeDracoMesh(bytes);
    if (!mesh.ok()) return mesh.status();
    image = (*renderer)->RenderMesh(*mesh, *params, &info);
  } else {
    auto cloud = io::DecodeDracoPointCloud(bytes);
    if (!cloud.ok()) return cloud.status();
    image = (*renderer)->RenderPoints(*cloud, *params, &info);
  }
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return RenderedPicture{*std::move(png), info.color_min, info.color_max, info.renderer};
}

absl::StatusOr<RenderedPicture> JobService::RenderVolumeField(const std::string& id, const std::string& bytes,
                                                              const render::RenderParams& params,
                                                              const core::JobContext* ctx) {
  // The sampled grid of the last job drawn is kept: the frames of a turntable share it.
  const std::string key = core::StrCat(id, "/", params.volume_resolution);
  std::shared_ptr<const SampledVolume> sampled;
  {
    std::lock_guard lock(volume_mutex_);
    if (volume_key_ == key) sampled = volume_grid_;
  }
  if (sampled == nullptr) {
    auto field = volume::DeserializeVolumeField(bytes);
    if (!field.ok()) return field.status();
    auto grid = SampleVolumeForPicture(**field, params.volume_resolution, options_.max_render_bytes, ctx);
    if (!grid.ok()) return grid.status();
    sampled = std::make_shared<const SampledVolume>(*std::move(grid));
    std::lock_guard lock(volume_mutex_);
    volume_key_ = key;
    volume_grid_ = sampled;
  }
  // The GL's shader on a GPU; on Mesa's software rasterizer (or without a GL) the C++ ray
  // caster, which draws the same picture twice as fast there (measured: 0.24 s against 0.53 s
  // for 512² frames of the 384k-tetrahedra Marschner–Lobb mesh).
  render::RenderInfo info;
  auto renderer = renderer_->Get();
  const bool gpu = renderer.ok() && (*renderer)->description().find("llvmpipe") == std::string::npos &&
                   (*renderer)->description().find("softpipe") == std::string::npos;
  auto image = gpu ? (*renderer)->RenderVolume(sampled->grid, params, &info)
                   : render::RaycastVolume(sampled->grid, params, &info);
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return RenderedPicture{*std::move(png), info.color_min,     info.color_max,
                         info.renderer,   sampled->rms_error, sampled->max_error};
}

bool JobService::CanRender() { return renderer_->Get().ok(); }

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

std::shared_ptr<DecodedInput> JobService::ReleaseDecoded(const std::string& id) {
  auto it = decoded_.find(id);
  if (it == decoded_.end()) return nullptr;
  decoded_points_ -= it->second.points;
  std::shared_ptr<DecodedInput> input = std::move(it->second.input);
  decoded_.erase(it);
  return input;
}

std::shared_ptr<JobService::Entry> JobService::ClaimNext(std::shared_ptr<DecodedInput>* decoded) {
  auto claimed = store_->Claim(runner_, options_.lease);
  if (!claimed.ok()) {
    // Once per outage, not at every poll of every worker.
    if (!claims_failing_.exchange(true))
      spdlog::error("cannot take jobs from the store: {}", claimed.status().ToString());
    return nullptr;
  }
  claims_failing_ = false;
  if (!claimed->has_value()) return nullptr;
  std::shared_ptr<Entry> entry;
  {
    std::lock_guard lock(mutex_);
    *decoded = ReleaseDecoded((*claimed)->id);
    entry = Adopt(**std::move(claimed));
    entry->held = true;
    // A cancellation that reached the store between the claim and this line is in the record
    // kept (Adopt keeps the newer one); the run must see it, as no one will tell it again.
    entry->cancel_requested = entry->record.cancel_requested;
    entry->lost = false;
    // A shutdown that began during the claim has marked the held jobs already: this one goes
    // back to the queue at once instead of running until it ends.
    entry->interrupted = shutting_down_;
  }
  NotifyChanged();
  return entry;
}

void JobService::WorkerLoop() {
  for (;;) {
    uint64_t signal = 0;
    {
      std::lock_guard lock(mutex_);
      if (shutting_down_) return;
      signal = work_signal_;
    }
    std::shared_ptr<DecodedInput> decoded;
    if (std::shared_ptr<Entry> entry = ClaimNext(&decoded)) {
      RunJob(entry, std::move(decoded));
      continue;
    }
    // Nothing to claim: wait for a submission, another service's job, or the next poll.
    std::unique_lock lock(mutex_);
    const auto woken = [&] { return shutting_down_ || work_signal_ != signal; };
    // A store of its own gets jobs only through Submit; the long wait there only guards
    // against a claim that failed.
    work_available_.wait_for(lock, store_->shared() ? options_.poll : std::chrono::milliseconds(10'000), woken);
  }
}

absl::StatusOr<Statistics> JobService::RunKind(const std::shared_ptr<Entry>& entry, BlobSink& sink,
                                               std::shared_ptr<DecodedInput> decoded) {
  // The run works on its own copy: the record is replaced whenever its state is stored.
  JobRecord record;
  {
    std::lock_guard lock(mutex_);
    record = entry->record;
  }
  Uploads uploads;
  // A decoded input stands in for the uploads; without one they are read back.
  for (const auto& [slot, blob] : UploadFiles()) {
    if (decoded != nullptr) break;
    if (!blobs_->Exists(record.id, blob)) continue;
    auto bytes = blobs_->Read(record.id, blob);
    if (!bytes.ok()) return bytes.status();
    uploads[slot] = *std::move(bytes);
  }
  const JobKind* kind = KindOf(record.spec.method);
  if (kind == nullptr) return absl::FailedPreconditionError(core::StrCat("no method '", record.spec.method, "'"));
  Context ctx(*this, entry, record.spec.method);
  struct StageEnd {
    Context& ctx;
    ~StageEnd() { ctx.Finish(); }
  } stage_end{ctx};
  // Only the jobs the spec names, whose visibility to the submitter Submit checked.
  const std::vector<std::string> referenced = kind->ReferencedJobs(record.spec);
  RunEnvironment env{sink,
                     ctx,
                     renderer_.get(),
                     std::move(decoded),
                     [this, referenced](const std::string& id, const std::string& name) -> absl::StatusOr<std::string> {
                       if (std::find(referenced.begin(), referenced.end(), id) == referenced.end())
                         return NoSuchJob(id);
                       auto reader = OpenResult(id, name);
                       if (!reader.ok()) return reader.status();
                       return ReadAll(**reader);
                     },
                     options_.max_job_memory};
  try {
    return kind->Run(record.spec, uploads, env);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("the job ran out of memory");
  } catch (const std::exception& e) {
    return absl::InternalError(core::StrCat("engine error: ", e.what()));
  }
}

void JobService::RunJob(const std::shared_ptr<Entry>& entry, std::shared_ptr<DecodedInput> decoded) {
  const std::string id = entry->record.id;
  const auto run_start = std::chrono::steady_clock::now();
  if (entry->record.state == JobState::kFailed) {
    // Its stored spec no longer decodes here: the claim read it back failed, with the reason.
    Update(entry, [](JobRecord&) {});
  } else {
    spdlog::info("[job {}] started (attempt {})", id, entry->record.attempts);
    const auto start = std::chrono::steady_clock::now();
    BlobSink sink(*blobs_, id, [this, &entry](int64_t artifact_bytes) { return AdmitResults(entry, artifact_bytes); });
    absl::StatusOr<Statistics> result = RunKind(entry, sink, std::move(decoded));
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (entry->lost) {
      spdlog::warn("[job {}] ran {:.2f} s under a lapsed lease; its outcome is dropped", id, seconds);
      // Should the store still show it as this server's, it goes back to the queue, not held
      // against it; otherwise the write is refused and the store's state stands.
      Update(entry, [](JobRecord& r) {
        r.state = JobState::kQueued;
        r.stage.clear();
        r.progress = 0;
        ++r.interruptions;
      });
    } else if (result.ok()) {
      Update(entry, [&](JobRecord& r) {
        r.state = JobState::kSucceeded;
        r.stage = "done";
        r.progress = 1;
        r.statistics = *std::move(result);
        r.statistics.emplace_back("wall_seconds", seconds);
        r.results = sink.names();
        r.stored_bytes = r.input_bytes + sink.bytes();
      });
      spdlog::info("[job {}] succeeded in {:.2f} s", id, seconds);
    } else if (entry->interrupted && !entry->cancel_requested &&
               result.status().code() == absl::StatusCode::kCancelled) {
      // Interrupted by a shutdown, and nobody asked to cancel it: it runs again later.
      Update(entry, [](JobRecord& r) {
        r.state = JobState::kQueued;
        r.stage.clear();
        r.progress = 0;
        ++r.interruptions;  // A shutdown is not the job's fault.
      });
      spdlog::info("[job {}] interrupted by shutdown; will resume on restart", id);
    } else if (result.status().code() == absl::StatusCode::kCancelled) {
      // What it wrote stays with it (until it is deleted), so it counts as stored.
      Update(entry, [&](JobRecord& r) {
        r.state = JobState::kCancelled;
        r.error = "cancelled by request";
        r.cancel_requested = false;
        r.stored_bytes = r.input_bytes + sink.bytes();
      });
      spdlog::info("[job {}] cancelled after {:.2f} s", id, seconds);
    } else {
      Update(entry, [&](JobRecord& r) {
        r.state = JobState::kFailed;
        r.error = std::string(result.status().message());
        r.stored_bytes = r.input_bytes + sink.bytes();
      });
      spdlog::warn("[job {}] failed: {}", id, result.status().ToString());
    }
  }
  if (options_.events != nullptr) {
    JobRecord ended;
    {
      std::lock_guard lock(mutex_);
      ended = entry->record;
    }
    options_.events->JobEnded(ended.spec.method, ended.state,
                              std::chrono::duration<double>(std::chrono::steady_clock::now() - run_start).count());
  }
  {
    std::lock_guard lock(mutex_);
    entry->held = false;
    if (!entry->lost && !entry->removed_elsewhere) return;
    entry->record.seq = 0;  // Whatever the store holds now replaces this run's view.
  }
  auto stored = store_->Get(id);
  {
    std::lock_guard lock(mutex_);
    if (stored.ok()) {
      Adopt(*std::move(stored));
    } else if (stored.status().code() == absl::StatusCode::kNotFound) {
      // Deleted elsewhere while it ran here: nothing of it stays on this server either.
      if (auto it = jobs_.find(id); it != jobs_.end() && it->second == entry) {
        ReleaseDecoded(id);
        jobs_.erase(it);
      }
    }
  }
  NotifyChanged();
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

void JobService::RenewLeases() {
  std::vector<std::string> running;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, e] : jobs_) {
      if (e->held && !e->lost) running.push_back(id);
    }
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
