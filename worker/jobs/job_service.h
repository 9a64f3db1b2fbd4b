// worker/jobs/job_service.h — accepts, stores, schedules and runs jobs of every kind.
//
// The server's single entry point into the workers; it knows nothing of gRPC, and nothing of
// a kind's details (those live behind JobKind). Specs are validated once here (ValidateSpec),
// uploads by the job's kind, before a job is accepted; an accepted job is on disk (a store
// record + its uploads) before Submit returns and is never lost: after a restart, queued jobs
// run, and jobs that were running are queued again, then failed with a reason once they have
// crashed the server `max_attempts` times (a graceful shutdown does not count).
//
// Threading: a fixed pool of `workers` threads runs jobs from a bounded FIFO queue; every
// public method is thread-safe. Store writes happen outside the service's lock, so reads
// (Get, List, WaitForChange) never wait on the disk. Submit decodes the uploads to check them
// (~0.3 s per million points, on the caller's thread) and keeps the decoded input for the run
// while the queued jobs' decoded inputs hold at most `max_points` points (else, and after a
// restart, the run decodes the stored upload again); Render draws on the caller's thread with at
// most `max_renders` at once.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/blob_store.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/job_store.h"

namespace lsqsurf::render {
class SharedRenderer;
struct RenderParams;
}  // namespace lsqsurf::render

namespace lsqsurf::jobs {

struct SampledVolume;  // volume_job.h

struct JobServiceOptions {
  std::string data_dir;                        // Holds jobs.db and one folder per job; created if missing.
  int workers = 1;                             // Jobs that run at once (each uses every core).
  int max_queue = 64;                          // Queued jobs beyond which Submit is refused.
  int64_t max_points = 20'000'000;             // Largest accepted cloud.
  int64_t min_points = 16;                     // Smallest accepted surface cloud.
  int64_t max_cells = 100'000'000;             // Largest accepted volume mesh (its vertices count as points).
  int64_t max_input_bytes = int64_t{1} << 30;  // Largest accepted upload (all slots together).
  int max_attempts = 2;                        // Crashed starts before a job is failed.
  int max_renders = 2;                         // Render calls drawn at once; more get kResourceExhausted.
  // Where uploads and artifacts are kept; null: files under data_dir/jobs.
  std::shared_ptr<BlobStore> blobs;
  // Tests only: replaces the kind that runs a method's jobs (e.g. one that blocks on a latch).
  std::map<std::string, const JobKind*> kind_overrides;
};

// A picture of a result.
struct RenderedPicture {
  std::string png;
  double color_min = 0, color_max = 0;            // The colour range used, when colouring.
  std::string renderer;                           // The GL renderer that drew it.
  double grid_rms_error = 0, grid_max_error = 0;  // Volume fields: the sampled grid against the field.
};

class JobService {
 public:
  // Opens the store and recovers the jobs of a previous run. Errors: kUnavailable, kInvalidArgument.
  static absl::StatusOr<std::unique_ptr<JobService>> Open(const JobServiceOptions& options);
  ~JobService();  // Calls Shutdown().

  // Validates and enqueues. Errors: kInvalidArgument (bad method, parameter, preview, or
  // upload, with the reason), kResourceExhausted (queue full, too many points or bytes),
  // kUnavailable (shutting down, storage failure, or a preview asked of a server that cannot
  // draw).
  absl::StatusOr<JobRecord> Submit(const JobSpec& spec, Uploads uploads);

  absl::StatusOr<JobRecord> Get(const std::string& id) const;
  std::vector<JobRecord> List() const;  // Newest first.
  // Requests cancellation: a queued job ends at once (the returned record is CANCELLED); a
  // running one stops within about a second (the returned record is still RUNNING; CANCELLED
  // follows). Errors: kNotFound, kFailedPrecondition (already finished).
  absl::StatusOr<JobRecord> Cancel(const std::string& id);
  // Removes a finished job and its files. Errors: kNotFound, kFailedPrecondition (not finished).
  absl::Status Delete(const std::string& id);
  // A result artifact for reading; an empty name means the job's first result. Errors:
  // kNotFound (job or artifact), kFailedPrecondition (not succeeded).
  absl::StatusOr<std::unique_ptr<BlobReader>> OpenResult(const std::string& id, const std::string& name) const;
  // Draws a Draco artifact (a mesh or a point set) with view options from DefaultView().
  // Errors: those of OpenResult, kInvalidArgument (bad view, not geometry), kUnavailable (no
  // renderer), kResourceExhausted (max_renders pictures being drawn).
  absl::StatusOr<RenderedPicture> Render(const std::string& id, const std::string& name, const core::ParamSet& view);

  // Blocks until the job's version differs from `seen_version`, the timeout passes, or the
  // service shuts down; returns the current record. Errors: kNotFound.
  absl::StatusOr<JobRecord> WaitForChange(const std::string& id, uint64_t seen_version,
                                          std::chrono::milliseconds timeout) const;

  // Stops accepting work; running jobs are interrupted and put back in the queue on disk (their
  // interruption is counted, not held against them), so the next start resumes them. Idempotent.
  void Shutdown();

  const JobServiceOptions& options() const { return options_; }
  // Whether pictures can be drawn (makes the renderer on first use, about 0.1 s).
  bool CanRender();
  bool shutting_down() const {
    std::lock_guard lock(mutex_);
    return shutting_down_;
  }

 private:
  struct Entry;
  class Context;
  explicit JobService(JobServiceOptions options);
  void WorkerLoop();
  void RunJob(const std::shared_ptr<Entry>& entry, std::shared_ptr<void> decoded);
  // Takes the entry's decoded input out of the memory budget (mutex_ held).
  std::shared_ptr<void> ReleaseDecoded(Entry& entry);
  absl::StatusOr<Statistics> RunKind(const std::shared_ptr<Entry>& entry, class BlobSink& sink,
                                     std::shared_ptr<void> decoded);
  // Applies `change` to the record under the lock, wakes watchers, then persists it.
  void Update(const std::shared_ptr<Entry>& entry, const std::function<void(JobRecord&)>& change, bool persist = true);
  void Persist(const std::shared_ptr<Entry>& entry, const JobRecord& copy);
  const JobKind* KindOf(const std::string& method) const;
  // A picture of a volume job's stored field (the Render path for field.lqvf).
  absl::StatusOr<RenderedPicture> RenderVolumeField(const std::string& id, const std::string& bytes,
                                                    const render::RenderParams& params);

  JobServiceOptions options_;
  std::unique_ptr<render::SharedRenderer> renderer_;
  std::unique_ptr<JobStore> store_;
  std::shared_ptr<BlobStore> blobs_;
  std::mutex store_mutex_;  // Orders store writes (never held with mutex_).
  std::atomic<int> renders_{0};
  std::mutex volume_mutex_;  // Guards the two below: the last volume grid drawn and its key.
  std::string volume_key_;
  std::shared_ptr<const SampledVolume> volume_grid_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;  // Any job changed (watchers).
  std::condition_variable work_available_;   // Queue gained a job or shutdown began.
  std::map<std::string, std::shared_ptr<Entry>> jobs_;
  std::deque<std::shared_ptr<Entry>> queue_;
  std::vector<std::thread> workers_;
  bool shutting_down_ = false;
  int64_t decoded_points_ = 0;  // Points of the decoded inputs queued jobs hold (mutex_).
};

}  // namespace lsqsurf::jobs
