// worker/jobs/job_runner.h — the worker threads of a service: each claims the oldest queued job
// from the store, runs its kind with a progress and cancellation context and an artifact sink
// held to the job's quota, and records how it ended; with a shared store, a worker runs the tiles
// of other servers' tiled builds first, then new jobs.
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
  // Holds (held true) or drops the lease renewals of a tile this service runs (JobReplication).
  using HoldTile = std::function<void(const TileTask& task, bool held)>;
  struct Parts {
    JobTable& table;
    DecodedInputs& decoded;
    JobAdmission& admission;
    JobPictures& pictures;
    JobStore& store;
    BlobStore& blobs;
    HoldTile hold_tile;
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
  // Claims the oldest queued job; null when none is queued or the store failed.
  std::shared_ptr<JobEntry> ClaimNext(std::shared_ptr<DecodedInput>* decoded);
  void RunJob(const std::shared_ptr<JobEntry>& entry, std::shared_ptr<DecodedInput> decoded);
  absl::StatusOr<Statistics> RunKind(const std::shared_ptr<JobEntry>& entry, BlobSink& sink,
                                     std::shared_ptr<DecodedInput> decoded);
  // Shared stores: runs one tile of another job spread over the servers; false when none waits.
  bool RunOthersTile();
  // How this service claims and runs tiles (its lease, attempt limit and tile format).
  TileClaimOptions TileClaims() const;

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
  // Set once a tile of another server's job could not be read from this server's blob store: it
  // takes no more tiles (each would only wait out its lease).
  std::atomic<bool> tiles_unreadable_{false};
};

}  // namespace lsqsurf::jobs
