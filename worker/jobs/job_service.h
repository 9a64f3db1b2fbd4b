// worker/jobs/job_service.h — accepts, stores, schedules and runs jobs of every kind.
//
// The server's single entry point into the workers; it knows nothing of gRPC, and nothing of
// a kind's details (those live behind JobKind). Specs are validated once here (ValidateSpec),
// uploads by the job's kind, before a job is accepted; an accepted job is stored (a store
// record + its uploads) before Submit returns and is never lost: after a restart, queued jobs
// run, and jobs that were running are queued again, then failed with a reason once they have
// crashed a server `max_attempts` times (a graceful shutdown does not count).
//
// The job store (job_store.h) is where jobs are queued and claimed. With a store of its own
// (SQLite, the default) this service is the only one to run its jobs. With a shared store
// (PostgreSQL) several services take jobs from one queue: each claims a job under a lease that
// a background thread renews, follows the others' changes (a notification, else polling every
// `poll`), passes cancellations on to the runner, and recovers the jobs of a service whose
// lease lapsed. Jobs, results and pictures can then be asked of any of them.
//
// Threading: a fixed pool of `workers` threads claims and runs jobs in FIFO order; every
// public method is thread-safe. The service keeps every job's record in memory and writes to
// the store outside its lock, so reads (Get, List, WaitForChange) never wait on the store.
// Submit decodes the uploads to check them (~0.3 s per million points, on the caller's thread)
// and keeps the decoded input for the run while the queued jobs' decoded inputs hold at most
// `max_points` points (else, and after a restart, the run decodes the stored upload again);
// Render draws on the caller's thread with at most `max_renders` at once.
//
// The service is its parts, each a class with its own state: the record table (job_table.h),
// admission (job_admission.h), the runner (job_runner.h), replication (job_replication.h),
// retention (job_retention.h) and pictures (job_pictures.h).
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_service_options.h"
#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"

namespace lsqsurf::jobs {

class DecodedInputs;
class JobTable;
class JobAdmission;
class JobRetention;
class JobRunner;
class JobReplication;
class JobPictures;

class JobService {
 public:
  using Usage = JobUsage;

  // Opens the store and recovers the jobs of a previous run. Errors: kUnavailable, kInvalidArgument.
  static absl::StatusOr<std::unique_ptr<JobService>> Open(const JobServiceOptions& options);
  ~JobService();  // Calls Shutdown().

  // Validates and enqueues. Errors: kInvalidArgument (bad method, parameter, preview, or
  // upload, with the reason), kResourceExhausted (queue full, too many points or bytes),
  // kUnavailable (shutting down, storage failure, or a preview asked of a server that cannot
  // draw); kResourceExhausted also for a submitter over a quota.
  absl::StatusOr<JobRecord> Submit(const JobSpec& spec, Uploads uploads, const Submitter& submitter = {});
  // Upload limits, usage and stored bytes (JobAdmission::MaxUploadBytes, UsageOf, StoredBytes).
  const JobAdmission& admission() const { return *admission_; }
  // Deletion: of a finished job with its files (JobRetention::Delete; errors: kNotFound,
  // kFailedPrecondition when not finished), and by age and size (JobRetention::SweepFinished, run
  // every `sweep_interval` on its own thread, and at Submit).
  JobRetention& retention() { return *retention_; }

  absl::StatusOr<JobRecord> Get(const std::string& id) const;
  // The one answer to "may `who` see job `id`": the record when it is theirs (or they see all),
  // else kNotFound word for word as for a missing job, so that nothing tells the two apart. Every
  // path to a job goes through it: the rpcs that name one, and the jobs a spec refers to.
  absl::StatusOr<JobRecord> GetFor(const Submitter& who, const std::string& id) const;
  std::vector<JobRecord> List() const;  // Newest first.
  // Requests cancellation: a queued job ends at once (the returned record is CANCELLED); a
  // running one stops within about a second (the returned record is still RUNNING; CANCELLED
  // follows). Errors: kNotFound, kFailedPrecondition (already finished).
  absl::StatusOr<JobRecord> Cancel(const std::string& id);
  // A result artifact for reading; an empty name means the job's first result. Errors:
  // kNotFound (job or artifact), kFailedPrecondition (not succeeded).
  absl::StatusOr<std::unique_ptr<BlobReader>> OpenResult(const std::string& id, const std::string& name) const;
  // Draws a Draco artifact (a mesh or a point set) or a volume field, with view options from
  // DefaultView(), for `who`. A mesh part (named, or the first result) stands for the mesh
  // delivered in parts: every part listed so far is drawn, one held at a time, so a running job
  // shows the surface done so far (another's job answers as a missing one). A named user holds at most
  // half of the max_renders slots (rounded up), so that no one holds all of them; `ctx` (may be
  // null) stops the drawing once its caller has gone. Errors: those of OpenResult,
  // kInvalidArgument (bad view, not geometry), kUnavailable (no renderer), kResourceExhausted
  // (the slots taken, or a volume grid past max_render_bytes), kCancelled.
  absl::StatusOr<RenderedPicture> Render(const Submitter& who, const std::string& id, const std::string& name,
                                         const core::ParamSet& view, const core::JobContext* ctx = nullptr);
  // Whether pictures can be drawn (makes the renderer on first use, about 0.1 s).
  bool CanRender();

  // Blocks until the job's version differs from `seen_version`, the timeout passes, or the
  // service shuts down; returns the current record. Errors: kNotFound.
  absl::StatusOr<JobRecord> WaitForChange(const std::string& id, uint64_t seen_version,
                                          std::chrono::milliseconds timeout) const;

  // Blocks until any job changes after the count `seen` (0 at first), the timeout passes, or the
  // service shuts down; returns the count of changes now. Lets one thread serve many watchers.
  uint64_t WaitForAnyChange(uint64_t seen, std::chrono::milliseconds timeout) const;

  // Stops accepting work; running jobs are interrupted and put back in the queue on disk (their
  // interruption is counted, not held against them), so the next start resumes them. Idempotent.
  void Shutdown();

  const JobServiceOptions& options() const { return options_; }
  // This service's runner name (a job's runner while this service runs it).
  const std::string& runner() const { return runner_; }
  // Whether the store answered this service's last look (always true for a store of its own):
  // a server whose shared store is gone cannot take or report jobs, so it should not be sent any.
  bool StoreReachable() const;
  bool shutting_down() const;

 private:
  explicit JobService(JobServiceOptions options);

  JobServiceOptions options_;
  std::string runner_;
  std::string scratch_dir_;  // data_dir/scratch: RunEnvironment::scratch_dir.
  std::shared_ptr<JobStore> store_;
  std::shared_ptr<BlobStore> blobs_;
  // The parts, in the order they are made (each refers to those before it) and the reverse of
  // the order they go.
  std::unique_ptr<DecodedInputs> decoded_;
  std::unique_ptr<JobTable> table_;
  std::unique_ptr<JobPictures> pictures_;
  std::unique_ptr<JobRetention> retention_;
  std::unique_ptr<JobAdmission> admission_;
  std::unique_ptr<JobReplication> replication_;
  std::unique_ptr<JobRunner> runner_threads_;
  std::mutex shutdown_mutex_;  // Orders Shutdown's steps when called from two threads.
};

}  // namespace lsqsurf::jobs
