// worker/jobs/job_service_internal.h — what the job service's parts (job_service.cc: the record
// table; job_admission.cc; job_retention.cc; job_runner.cc; job_replication.cc; job_pictures.cc)
// share. Only those files include it.
#pragma once

#include <atomic>
#include <cstdint>
#include <map>
#include <string>

#include "worker/jobs/job_service.h"

namespace lsqsurf::jobs {

inline int64_t MiB(int64_t bytes) { return (bytes + (int64_t{1} << 20) - 1) >> 20; }

// Milliseconds since the epoch, what records keep.
int64_t NowMs();

// Where each upload slot is kept in a job's folder (names kept from earlier versions).
const std::map<std::string, std::string>& UploadFiles();
// The blob of an upload slot: UploadFiles(), and "input.n.drc" for input part n > 0.
std::string UploadBlob(const std::string& slot);

// The new state of a job whose runner stopped while it ran: cancelled if that was asked for,
// queued again, or failed once such stops add up to `max_attempts`.
void RecoverStoppedRun(JobRecord& r, int max_attempts);

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

}  // namespace lsqsurf::jobs
