// worker/jobs/job_service.h — accepts, stores, schedules and runs reconstruction jobs.
//
// The server's single entry point into the workers; it knows nothing of gRPC. Inputs are
// validated completely before a job is accepted (so a bad upload is refused at once, with a
// message that says what is wrong); an accepted job is on disk (SQLite row + input file)
// before Submit returns and is never lost: after a restart, queued jobs run, and jobs that
// were running are queued again once, then failed with a reason.
//
// Threading: a fixed pool of `workers` threads runs jobs from a bounded FIFO queue; every
// public method is thread-safe and returns quickly (no engine work happens on the caller's
// thread; Submit decodes the upload to validate it, ~0.3 s per million points).
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_store.h"

namespace lsqsurf::jobs {

struct JobServiceOptions {
  std::string data_dir;                  // Holds jobs.db and one folder per job; created if missing.
  int workers = 1;                       // Jobs that run at once (each uses every core).
  int max_queue = 64;                    // Queued jobs beyond which Submit is refused.
  int64_t max_points = 20'000'000;       // Largest accepted cloud.
  int64_t max_input_bytes = int64_t{1} << 30;  // Largest accepted upload.
  int max_attempts = 2;                  // Starts before an interrupted job is failed.
};

class JobService {
 public:
  // Opens the store and recovers the jobs of a previous run. Errors: kUnavailable, kInvalidArgument.
  static absl::StatusOr<std::unique_ptr<JobService>> Open(const JobServiceOptions& options);
  ~JobService();  // Calls Shutdown().

  // Validates and enqueues. `input` is a Draco point cloud; `velocity` a legacy VTK vector grid,
  // only for the track method with field = 2. Errors: kInvalidArgument (bad method,
  // parameter, preview, or input, with the reason), kResourceExhausted (queue full, too many
  // points or bytes), kUnavailable (shutting down, storage failure, or a preview asked of a
  // server that cannot draw).
  absl::StatusOr<JobRecord> Submit(const JobSpec& spec, std::string input, std::string velocity = {});

  absl::StatusOr<JobRecord> Get(const std::string& id) const;
  std::vector<JobRecord> List() const;  // Newest first.
  // Requests cancellation: a queued job ends at once, a running one within about a second.
  // Errors: kNotFound, kFailedPrecondition (already finished).
  absl::StatusOr<JobRecord> Cancel(const std::string& id);
  // Removes a finished job and its files. Errors: kNotFound, kFailedPrecondition (not finished).
  absl::Status Delete(const std::string& id);
  // Path of a result artifact. Errors: kNotFound (job or artifact), kFailedPrecondition (not done).
  absl::StatusOr<std::string> ResultPath(const std::string& id, const std::string& name) const;

  // Blocks until the job's version differs from `seen_version`, the timeout passes, or the
  // service shuts down; returns the current record. Errors: kNotFound.
  absl::StatusOr<JobRecord> WaitForChange(const std::string& id, uint64_t seen_version,
                                          std::chrono::milliseconds timeout) const;

  // Stops accepting work; running jobs are interrupted and put back in the queue on disk (their
  // attempt is not counted), so the next start resumes them. Idempotent.
  void Shutdown();

  const JobServiceOptions& options() const { return options_; }
  // The process's renderer (previews of jobs, and pictures on request), made on first use.
  render::SharedRenderer& renderer() { return renderer_; }
  bool shutting_down() const {
    std::lock_guard lock(mutex_);
    return shutting_down_;
  }

 private:
  struct Entry;
  class Context;
  explicit JobService(JobServiceOptions options) : options_(std::move(options)) {}
  void WorkerLoop();
  void RunJob(const std::shared_ptr<Entry>& entry);
  // Applies `change` to the record under the lock, persists it and wakes watchers.
  void Update(const std::shared_ptr<Entry>& entry, const std::function<void(JobRecord&)>& change,
              bool persist = true);
  std::string JobDir(const std::string& id) const;

  JobServiceOptions options_;
  render::SharedRenderer renderer_;
  std::unique_ptr<JobStore> store_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;   // Any job changed (watchers).
  std::condition_variable work_available_;    // Queue gained a job or shutdown began.
  std::map<std::string, std::shared_ptr<Entry>> jobs_;
  std::deque<std::shared_ptr<Entry>> queue_;
  std::vector<std::thread> workers_;
  bool shutting_down_ = false;
};

}  // namespace lsqsurf::jobs
