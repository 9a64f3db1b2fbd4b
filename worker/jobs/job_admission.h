// worker/jobs/job_admission.h — what a service accepts: a spec and its uploads checked, the
// server's limits, per-user quotas and fairness, room in the store, the memory a job may take;
// then the accepted job stored and queued; and, while jobs run, their results held to the quota.
//
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>

#include "absl/status/statusor.h"
#include "worker/jobs/job_pictures.h"
#include "worker/jobs/job_retention.h"
#include "worker/jobs/job_service_options.h"
#include "worker/jobs/job_table.h"

namespace lsqsurf::jobs {

// Thread-safe.
class JobAdmission {
 public:
  // `wake_workers` is told when a job was queued.
  JobAdmission(const JobServiceOptions& options, JobTable& table, DecodedInputs& decoded, JobRetention& retention,
               JobPictures& pictures, JobStore& store, BlobStore& blobs, std::function<void()> wake_workers)
      : options_(options),
        table_(table),
        decoded_(decoded),
        retention_(retention),
        pictures_(pictures),
        store_(store),
        blobs_(blobs),
        wake_workers_(std::move(wake_workers)) {}

  // JobService::Submit.
  absl::StatusOr<JobRecord> Submit(const JobSpec& spec, Uploads uploads, const Submitter& submitter);
  // The largest upload `submitter` may send: their limit or the server's, whichever is less.
  int64_t MaxUploadBytes(const Submitter& submitter) const;
  JobUsage UsageOf(const std::string& owner) const;
  // Bytes every job keeps together (uploads and results), submissions being stored included.
  int64_t StoredBytes() const;
  // Admits a running job's artifacts that would take `artifact_bytes` in all: refused past the
  // quota recorded with the job; counted in its stored bytes at once.
  absl::Status AdmitResults(const std::shared_ptr<JobEntry>& entry, int64_t artifact_bytes);

 private:
  JobUsage OwnerUsage(const JobEntries& jobs, const std::string& owner) const;  // mutex_ and the table's lock held.
  // Refuses a job of `job_bytes` that would take `submitter` past a quota (mutex_ held).
  absl::Status CheckQuota(const Submitter& submitter, int64_t job_bytes) const;
  // Refuses an upload that the store has no room for (max_store_bytes, min_free_bytes).
  absl::Status CheckRoom(int64_t job_bytes);

  const JobServiceOptions& options_;
  JobTable& table_;
  DecodedInputs& decoded_;
  JobRetention& retention_;
  JobPictures& pictures_;
  JobStore& store_;
  BlobStore& blobs_;
  const std::function<void()> wake_workers_;
  mutable std::mutex mutex_;                 // Taken before the table's lock, never after it.
  std::map<std::string, JobUsage> pending_;  // Submissions being stored, by owner (mutex_).
};

}  // namespace lsqsurf::jobs
