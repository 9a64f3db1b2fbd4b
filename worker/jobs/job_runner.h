// worker/jobs/job_runner.h — the worker threads of a service: each claims the oldest queued job
// from the store, runs its kind with a progress and cancellation context and an artifact sink
// held to the job's quota, and records how it ended. Child jobs (the tiles of tiled builds on a
// shared store) are claimed before new jobs.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job_admission.h"
#include "worker/jobs/job_pictures.h"
#include "worker/jobs/job_service_options.h"
#include "worker/jobs/job_table.h"
#include "worker/jobs/tile_exchange.h"

namespace lsqsurf::jobs {

class BlobSink;  // job_runner.cc

// Thread-safe.
class JobRunner {
 public:
  struct Parts {
    JobTable& table;
    DecodedInputs& decoded;
    JobAdmission& admission;
    JobPictures& pictures;
    JobStore& store;
    BlobStore& blobs;
  };
  // `runner` is this service's name in the store; `scratch_dir` where runs keep large temporaries.
  JobRunner(const JobServiceOptions& options, std::string runner, std::string scratch_dir, Parts parts)
      : options_(options), runner_(std::move(runner)), scratch_dir_(std::move(scratch_dir)), parts_(std::move(parts)) {}
  ~JobRunner() { Stop(); }

  void Start();  // options.workers threads.
  // Interrupted runs end (JobTable::BeginShutdown marked them) and the threads are joined.
  void Stop();
  // A job may have been queued (a submission, another server's change): idle workers look.
  void WakeWorkers();

 private:
  void WorkerLoop();
  // Claims the oldest queued job within `scope`; null when none is queued or the store failed.
  std::shared_ptr<JobEntry> ClaimNext(const ClaimScope& scope, std::shared_ptr<DecodedInput>* decoded);
  // What this service claims: children of its own tile format first, then new jobs.
  ClaimScope Scope(const std::string& parent = "") const;
  void RunJob(const std::shared_ptr<JobEntry>& entry, std::shared_ptr<DecodedInput> decoded);
  absl::StatusOr<Statistics> RunKind(const std::shared_ptr<JobEntry>& entry, BlobSink& sink,
                                     std::shared_ptr<DecodedInput> decoded);
  // A tile's child job: its part of another job's tiled build (tile_exchange.h).
  absl::StatusOr<Statistics> RunTile(const std::shared_ptr<JobEntry>& entry, const JobRecord& record);
  // The table and workers as a tiled build's run follows and helps its tile jobs.
  TileJobs TileJobsOf();

  const JobServiceOptions& options_;
  const std::string runner_;
  const std::string scratch_dir_;
  Parts parts_;
  std::mutex mutex_;
  std::condition_variable work_available_;  // A job may have been queued, or Stop began.
  uint64_t work_signal_ = 0;                // Bumped whenever a job may have been queued (mutex_).
  bool stop_ = false;                       // mutex_.
  std::vector<std::thread> workers_;
  std::atomic<bool> claims_failing_{false};
};

}  // namespace lsqsurf::jobs
