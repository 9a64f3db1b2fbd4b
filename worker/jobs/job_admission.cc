#include "worker/jobs/job_admission.h"

#include <spdlog/spdlog.h>

#include <algorithm>

#include "absl/cleanup/cleanup.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/jobs/job_ids.h"
#include "worker/jobs/job_service_internal.h"
#include "worker/jobs/method_registry.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

namespace {

// Drops empty uploads and checks that the method takes the rest, input parts numbered without a
// gap. Returns the bytes uploaded.
absl::StatusOr<int64_t> CheckUploadSlots(const JobSpec& spec, const MethodInfo& method, Uploads& uploads) {
  int64_t bytes = 0;
  int64_t input_parts = 0;
  for (auto it = uploads.begin(); it != uploads.end();) {
    if (it->second.empty()) {
      it = uploads.erase(it);
      continue;
    }
    const auto& accepted = method.uploads;
    const int64_t part = InputPartOf(it->first);
    const bool in_parts = part > 0 && method.input_in_parts;
    if (!in_parts && std::find(accepted.begin(), accepted.end(), it->first) == accepted.end()) {
      return absl::InvalidArgumentError(core::StrCat("the ", spec.method, " method takes no '", it->first, "' upload",
                                                     part > 0 ? " (its input comes in one part)" : ""));
    }
    if (part >= 0) ++input_parts;
    bytes += static_cast<int64_t>(it->second.size());
    ++it;
  }
  if (input_parts != static_cast<int64_t>(InputParts(uploads).size())) {
    return absl::InvalidArgumentError("the input parts are not numbered 0, 1, 2, ... without a gap");
  }
  return bytes;
}

}  // namespace

namespace {

// Child jobs (a build's tiles) count as part of their build, which is counted already.
int QueuedJobs(const JobEntries& jobs) {
  int queued = 0;
  for (const auto& [id, e] : jobs) queued += e->record.state == JobState::kQueued && !IsChildJob(e->record);
  return queued;
}

int QueuedJobsOf(const JobEntries& jobs, const std::string& owner) {
  int queued = 0;
  for (const auto& [id, e] : jobs) {
    queued += e->record.state == JobState::kQueued && e->record.owner == owner && !IsChildJob(e->record);
  }
  return queued;
}

}  // namespace

absl::StatusOr<JobRecord> JobAdmission::Submit(const JobSpec& spec, Uploads uploads, const Submitter& submitter) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpec(spec));
  const JobKind* kind = KindFor(options_.kind_overrides, spec.method);
  // A job that reads another's results may name only jobs its submitter may see; the run reads
  // no others (JobRunner).
  for (const std::string& referenced : kind->ReferencedJobs(spec)) {
    if (!IsJobIdForm(referenced)) return absl::InvalidArgumentError(core::StrCat("a referenced ", kNotAJobId));
    auto record = table_.Get(referenced);
    if (!record.ok()) return record.status();
    if (!MayView(submitter, *record)) return NoSuchJob(referenced);
  }
  if (spec.preview.enabled) {
    if (absl::Status s = pictures_.RendererStatus(); !s.ok()) {
      return absl::UnavailableError(
          core::StrCat("this server cannot draw previews (", s.message(), "); submit the job without one"));
    }
  }
  const MethodEntry* method = FindMethod(spec.method);
  auto upload_bytes = CheckUploadSlots(spec, method->info, uploads);
  if (!upload_bytes.ok()) return upload_bytes.status();
  const int64_t bytes = *upload_bytes;
  if (const int64_t limit = MaxUploadBytes(submitter); bytes > limit) {
    return absl::ResourceExhaustedError(core::StrCat(
        "the upload has ", bytes, " bytes; ",
        limit < options_.max_input_bytes ? "your quota allows" : "this server accepts", " at most ", limit));
  }
  const int64_t spec_bytes = SpecBytes(spec);
  LSQSURF_RETURN_IF_ERROR(CheckRoom(bytes + ResultReserve(bytes) + spec_bytes));
  auto checked = kind->CheckUploads(spec, uploads,
                                    {options_.max_points, options_.min_points, options_.max_cells,
                                     options_.max_job_memory, MaxUploadBytes(submitter)});
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
  r.stored_bytes = bytes + ResultReserve(bytes) + spec_bytes;
  r.quota_bytes = submitter.max_stored_bytes;
  if (table_.shutting_down()) return absl::UnavailableError("the server is shutting down");
  {
    std::lock_guard lock(mutex_);
    const auto [queued, queued_of_owner] = table_.Locked([&](const JobEntries& jobs) {
      return std::pair{QueuedJobs(jobs), submitter.owner.empty() ? 0 : QueuedJobsOf(jobs, submitter.owner)};
    });
    if (queued >= options_.max_queue) {
      return absl::ResourceExhaustedError(
          core::StrCat("the job queue is full (", queued, " jobs waiting); try again later"));
    }
    // A named user may fill half of the queue (rounded up), so that others still get in.
    if (!submitter.owner.empty() && 2 * queued_of_owner >= options_.max_queue) {
      return absl::ResourceExhaustedError(core::StrCat("you have ", queued_of_owner,
                                                       " jobs waiting, half of this server's queue; submit more once "
                                                       "they have started"));
    }
    LSQSURF_RETURN_IF_ERROR(CheckQuota(submitter, r.stored_bytes));
    // Held against the quota until the job's entry counts itself.
    JobUsage& pending = pending_[submitter.owner];
    ++pending.active_jobs;
    pending.stored_bytes += r.stored_bytes;
  }
  const absl::Cleanup release_pending = [&] {
    std::lock_guard lock(mutex_);
    JobUsage& pending = pending_[submitter.owner];
    --pending.active_jobs;
    pending.stored_bytes -= r.stored_bytes;
    if (pending.active_jobs == 0) pending_.erase(submitter.owner);
  };
  for (const auto& [slot, data] : uploads) {
    // A spooled upload moves into the store (a rename where it can); others are written.
    const absl::Status s = data.movable_path().empty() ? blobs_.Put(r.id, UploadBlob(slot), data)
                                                       : blobs_.PutFile(r.id, UploadBlob(slot), data.movable_path());
    if (!s.ok()) {
      (void)blobs_.RemoveJob(r.id);
      return s;
    }
  }
  // The decoded input waits with the job while the waiting ones hold at most max_points points.
  // It is in place before the job is stored: a worker may claim it at once.
  decoded_.Keep(r.id, std::move(checked->decoded), r.input_points);
  // Stored before it is visible: a job the caller hears of survives a crash.
  if (absl::Status s = store_.Insert(r); !s.ok()) {
    (void)blobs_.RemoveJob(r.id);
    decoded_.Take(r.id);
    return s;
  }
  table_.Locked([&](JobEntries& jobs) {
    std::shared_ptr<JobEntry>& entry = jobs[r.id];
    // A worker may have claimed the job already; its entry stays.
    if (entry == nullptr) {
      entry = std::make_shared<JobEntry>();
      entry->record = r;
    }
    return 0;
  });
  wake_workers_();
  spdlog::info("[job {}] accepted: method {}, {} points, {} bytes", r.id, spec.method, r.input_points, r.input_bytes);
  return r;
}

int64_t JobAdmission::MaxUploadBytes(const Submitter& submitter) const {
  return submitter.max_upload_bytes > 0 ? std::min(submitter.max_upload_bytes, options_.max_input_bytes)
                                        : options_.max_input_bytes;
}

JobUsage JobAdmission::UsageOf(const std::string& owner) const {
  std::lock_guard lock(mutex_);
  return table_.Locked([&](const JobEntries& jobs) { return OwnerUsage(jobs, owner); });
}

int64_t JobAdmission::StoredBytes() const {
  std::lock_guard lock(mutex_);
  int64_t total = retention_.RecordedBytes();
  for (const auto& [owner, usage] : pending_) total += usage.stored_bytes;
  return total;
}

JobUsage JobAdmission::OwnerUsage(const JobEntries& jobs, const std::string& owner) const {
  JobUsage usage;
  if (auto it = pending_.find(owner); it != pending_.end()) usage = it->second;
  for (const auto& [id, e] : jobs) {
    if (e->record.owner != owner) continue;
    usage.active_jobs += !IsTerminal(e->record.state) && !IsChildJob(e->record);
    usage.stored_bytes += e->record.stored_bytes;
  }
  return usage;
}

absl::Status JobAdmission::CheckQuota(const Submitter& submitter, int64_t job_bytes) const {
  if (submitter.max_active_jobs <= 0 && submitter.max_stored_bytes <= 0) return absl::OkStatus();
  const JobUsage usage = table_.Locked([&](const JobEntries& jobs) { return OwnerUsage(jobs, submitter.owner); });
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

absl::Status JobAdmission::CheckRoom(int64_t job_bytes) {
  if (options_.max_store_bytes > 0 && StoredBytes() + job_bytes > options_.max_store_bytes) {
    retention_.SweepFinished(NowMs(), job_bytes);
    if (const int64_t kept = StoredBytes(); kept + job_bytes > options_.max_store_bytes) {
      return absl::ResourceExhaustedError(core::StrCat(
          "the server's store is full: its jobs keep ", kept, " of ", options_.max_store_bytes,
          " bytes and this job needs ", job_bytes,
          " (its upload and a reserve for its results); try again once jobs have finished and been deleted"));
    }
  }
  if (const int64_t available = blobs_.AvailableBytes();
      available >= 0 && available - job_bytes < options_.min_free_bytes) {
    return absl::ResourceExhaustedError(core::StrCat("the server's disk is nearly full (", available >> 20,
                                                     " MiB free, ", options_.min_free_bytes >> 20,
                                                     " MiB kept for running jobs); try again later"));
  }
  return absl::OkStatus();
}

absl::Status JobAdmission::AdmitResults(const std::shared_ptr<JobEntry>& entry, int64_t artifact_bytes) {
  std::lock_guard lock(mutex_);
  return table_.Locked([&](const JobEntries& jobs) -> absl::Status {
    JobRecord& r = entry->record;
    const int64_t total = r.input_bytes + SpecBytes(r.spec) + artifact_bytes;
    if (r.quota_bytes > 0) {
      const int64_t others = OwnerUsage(jobs, r.owner).stored_bytes - r.stored_bytes;
      if (others + total > r.quota_bytes) {
        return absl::ResourceExhaustedError(core::StrCat("the job's results would take your jobs past your quota of ",
                                                         r.quota_bytes, " stored bytes (the others keep ", others,
                                                         "); delete finished jobs to make room"));
      }
    }
    // The reservation stands until the run settles; past it, what was written counts at once.
    r.stored_bytes = std::max(r.stored_bytes, total);
    return absl::OkStatus();
  });
}

}  // namespace lsqsurf::jobs
