// worker/jobs/job_retention.h — how long finished jobs stay: deletion on request, by age
// (`retain`) and by the store's size (`max_store_bytes`), on a sweeping thread of its own; and,
// at start, the files no record owns.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/status.h"
#include "worker/jobs/job_table.h"
#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"

namespace lsqsurf::jobs {

struct RetentionLimits {
  std::chrono::seconds retain{0};  // JobServiceOptions::retain.
  int64_t max_store_bytes = 0;     // JobServiceOptions::max_store_bytes.
  std::chrono::milliseconds sweep_interval{60'000};
};

// Thread-safe.
class JobRetention {
 public:
  JobRetention(RetentionLimits limits, JobTable& table, JobStore& store, BlobStore& blobs)
      : limits_(limits), table_(table), store_(store), blobs_(blobs) {}
  ~JobRetention() { Stop(); }

  // Removes a finished job and its files. Errors: kNotFound, kFailedPrecondition (not finished).
  absl::Status Delete(const std::string& id);
  // Deletes the finished jobs that `retain` and `max_store_bytes` no longer allow as of `now_ms`
  // (Unix milliseconds), oldest first, leaving `room` bytes under max_store_bytes when it can.
  // Returns how many it deleted.
  int SweepFinished(int64_t now_ms, int64_t room = 0);
  // Bytes the jobs on record keep (uploads and results).
  int64_t RecordedBytes() const;
  // With a store of its own, at start: removes the files of jobs that are not on record (a crash
  // between an upload and its record, or during a deletion) and temporaries of cut writes.
  void RemoveOrphanedBlobs();
  // Sweeps every `sweep_interval` on a thread of its own, when there is a limit to keep.
  void Start();
  void Stop();  // Idempotent.

 private:
  const RetentionLimits limits_;
  JobTable& table_;
  JobStore& store_;
  BlobStore& blobs_;
  std::mutex mutex_;
  std::condition_variable wake_;
  bool stop_ = false;  // mutex_.
  std::thread thread_;
};

}  // namespace lsqsurf::jobs
