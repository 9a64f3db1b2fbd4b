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
// the store outside its lock, so reads (Get, List, WaitForChange) never wait on the store. Submit decodes the uploads
// to check them
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
#include "worker/core/fair_slots.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_events.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"

namespace lsqsurf::render {
class SharedRenderer;
struct RenderParams;
}  // namespace lsqsurf::render

namespace lsqsurf::jobs {

class VolumePictures;  // volume_job.h

// What a job's results are reckoned to take until its run settles them: as much as its upload.
// A reservation, counted against quotas and the store's limit from submission on, so that a user
// cannot queue more work than its quota holds; the run is held to the quota as it writes.
inline int64_t ResultReserve(int64_t upload_bytes) { return upload_bytes; }

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
  // Memory one Render may take for the grid of a volume picture (the rest of a picture is small);
  // a resolution that needs more is refused before anything is allocated.
  int64_t max_render_bytes = int64_t{1} << 30;
  // Memory one job may take: a job whose kind estimates more at submission is refused, and its
  // extraction stops past it (JobKind's LeavesWithin). -1: three quarters of this machine's
  // memory; 0: no limit.
  int64_t max_job_memory = -1;
  // Where uploads and artifacts are kept; null: files under data_dir/jobs.
  std::shared_ptr<BlobStore> blobs;
  // Where job records are kept and claimed; null: SQLite in data_dir/jobs.db.
  std::shared_ptr<JobStore> store;
  // This service's name among those sharing a store; a job's runner is this name and a suffix
  // drawn at start. Empty: the host name.
  std::string name;
  // A claimed job stays this service's for this long without a renewal (renewed every quarter
  // of it): a service that dies holds its jobs up to this long before another runs them.
  std::chrono::milliseconds lease{10'000};
  // Shared stores: how often to look for the others' changes when no notification comes.
  std::chrono::milliseconds poll{500};
  // Finished jobs (succeeded, failed, cancelled) are deleted this long after they ended, oldest
  // first; 0: kept until deleted.
  std::chrono::seconds retain{0};
  // Bytes all jobs may keep (uploads and results). Past it the oldest finished jobs are deleted
  // (never a queued or running one); when they are not enough, submissions are refused. 0: no limit.
  int64_t max_store_bytes = 0;
  // Submissions are refused while the blob store's disk would keep less than this free after the
  // upload, so that running jobs keep room for their results (stores that cannot tell: unchecked).
  int64_t min_free_bytes = int64_t{256} << 20;
  // How often finished jobs are looked at for deletion (with `retain` or `max_store_bytes`).
  std::chrono::milliseconds sweep_interval{60'000};
  // Told of stages and runs as they end (metrics); null: nobody.
  std::shared_ptr<JobEvents> events;
  // Tests only: replaces the kind that runs a method's jobs (e.g. one that blocks on a latch).
  std::map<std::string, const JobKind*> kind_overrides;
};

// A picture of a result.
struct RenderedPicture {
  std::string png;
  double color_min = 0, color_max = 0;            // The colour range used, when colouring.
  std::string renderer;                           // The GL renderer that drew it.
  double grid_rms_error = 0, grid_max_error = 0;  // Volume fields: the sampled grid against the field.
  int samples = 1;                                // Samples per pixel the GL drew with.
};

// Who submits a job or asks about one, and the limits that hold for them (0: none). Without
// tokens everyone is the same unnamed submitter without limits, who sees every job.
struct Submitter {
  std::string owner;             // Recorded as the job's owner.
  int max_active_jobs = 0;       // Their queued and running jobs.
  int64_t max_stored_bytes = 0;  // Their jobs' uploads and results, as stored.
  int64_t max_upload_bytes = 0;  // One job's upload (the server's limit holds as well).
  bool sees_all = true;          // Sees every job (an admin); else only those it owns.
};

class JobService {
 public:
  // What an owner's jobs hold now.
  struct Usage {
    int active_jobs = 0;       // Queued or running.
    int64_t stored_bytes = 0;  // Uploads and results.
  };

  // Opens the store and recovers the jobs of a previous run. Errors: kUnavailable, kInvalidArgument.
  static absl::StatusOr<std::unique_ptr<JobService>> Open(const JobServiceOptions& options);
  ~JobService();  // Calls Shutdown().

  // Validates and enqueues. Errors: kInvalidArgument (bad method, parameter, preview, or
  // upload, with the reason), kResourceExhausted (queue full, too many points or bytes),
  // kUnavailable (shutting down, storage failure, or a preview asked of a server that cannot
  // draw); kResourceExhausted also for a submitter over a quota.
  absl::StatusOr<JobRecord> Submit(const JobSpec& spec, Uploads uploads, const Submitter& submitter = {});
  // The largest upload `submitter` may send: their limit or the server's, whichever is less.
  int64_t MaxUploadBytes(const Submitter& submitter) const;
  Usage UsageOf(const std::string& owner) const;
  // Deletes the finished jobs that `retain` and `max_store_bytes` no longer allow as of `now_ms`
  // (Unix milliseconds), oldest first, leaving `room` bytes under max_store_bytes when it can.
  // Returns how many it deleted. Runs every `sweep_interval` on its own thread, and at Submit.
  int SweepFinished(int64_t now_ms, int64_t room = 0);
  // Bytes every job keeps together (uploads and results).
  int64_t StoredBytes() const;

  absl::StatusOr<JobRecord> Get(const std::string& id) const;
  // The one answer to "may `who` see job `id`": the record when it is theirs (or they see all),
  // else kNotFound word for word as for a missing job, so that nothing tells the two apart. Every
  // path to a job goes through it: the rpcs that name one, and the jobs a spec refers to.
  absl::StatusOr<JobRecord> GetFor(const Submitter& who, const std::string& id) const;
  static bool MayView(const Submitter& who, const JobRecord& record) {
    return who.sees_all || record.owner == who.owner;
  }
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
  // Whether pictures can be drawn (makes the renderer on first use, about 0.1 s).
  bool CanRender();
  // Whether the store answered this service's last look (always true for a store of its own):
  // a server whose shared store is gone cannot take or report jobs, so it should not be sent any.
  bool StoreReachable() const { return store_reachable_.load(); }
  bool shutting_down() const {
    std::lock_guard lock(mutex_);
    return shutting_down_;
  }

 private:
  struct Entry;
  class Context;
  explicit JobService(JobServiceOptions options);
  void WorkerLoop();
  // Claims the oldest queued job; null when none is queued or the store failed.
  std::shared_ptr<Entry> ClaimNext(std::shared_ptr<DecodedInput>* decoded);
  void RunJob(const std::shared_ptr<Entry>& entry, std::shared_ptr<DecodedInput> decoded);
  // Takes a job's decoded input out of the memory budget; null if none is kept (mutex_ held).
  std::shared_ptr<DecodedInput> ReleaseDecoded(const std::string& id);
  absl::StatusOr<Statistics> RunKind(const std::shared_ptr<Entry>& entry, class BlobSink& sink,
                                     std::shared_ptr<DecodedInput> decoded);
  // Applies `change` to the record and wakes watchers; with `persist`, stores the changed record
  // first (a held job's), so that what watchers see is in the store already.
  void Update(const std::shared_ptr<Entry>& entry, const std::function<void(JobRecord&)>& change, bool persist = true);
  // Writes a held job's record; its change number, or 0 when the write failed.
  int64_t Persist(const std::shared_ptr<Entry>& entry, const JobRecord& record);
  // Takes a record read from the store unless this service's copy is as new (mutex_ held).
  // Returns the entry (made if missing).
  std::shared_ptr<Entry> Adopt(JobRecord record);
  // The run's lease lapsed: it stops, logged once.
  static void MarkLost(Entry& entry, const std::string& id);
  // The job's entry, read from the store when this service has not seen it yet.
  std::shared_ptr<Entry> Find(const std::string& id) const;
  const JobKind* KindOf(const std::string& method) const;
  // A picture of every mesh part the record lists (the Render path for mesh-part-NNNNN.lqm).
  absl::StatusOr<RenderedPicture> RenderMeshParts(const JobRecord& record, const render::RenderParams& params);
  // A picture of a volume job's stored field (the Render path for field.lqvf).
  absl::StatusOr<RenderedPicture> RenderVolumeField(const std::string& id, const std::string& bytes,
                                                    const render::RenderParams& params, const core::JobContext* ctx);
  // Takes one of the max_renders slots for `owner`; false when none is left to them.
  bool TakeRenderSlot(const std::string& owner);
  void ReleaseRenderSlot(const std::string& owner);
  // Shared stores: follows the others' changes, renews leases, recovers lapsed ones.
  void SyncLoop();
  void SyncChanges();
  void RenewLeases();
  // Adds (or, with held false, drops) a tile this service runs to those whose leases it renews.
  void HoldTile(const TileTask& task, bool held);
  // Shared stores: runs one tile of another job spread over the servers; false when none waits.
  bool RunOthersTile();
  // Requeues (or fails, or cancels) the jobs of runners whose lease lapsed; every running job
  // with `every_running`.
  absl::Status RecoverLapsed(bool every_running);
  void NotifyChanged();                              // Counts a change and wakes the watchers (mutex_ not held).
  int QueuedJobs() const;                            // mutex_ held.
  int QueuedJobsOf(const std::string& owner) const;  // mutex_ held.
  // Admits a running job's artifacts that would take `artifact_bytes` in all: refused past the
  // quota recorded with the job; counted in its stored bytes at once.
  absl::Status AdmitResults(const std::shared_ptr<Entry>& entry, int64_t artifact_bytes);
  // At start with a store of its own: removes the files of jobs that are not on record (a crash
  // between an upload and its record, or during a deletion) and temporaries of cut writes.
  void RemoveOrphanedBlobs();
  Usage OwnerUsage(const std::string& owner) const;                              // mutex_ held.
  absl::Status CheckQuota(const Submitter& submitter, int64_t job_bytes) const;  // mutex_ held.
  // Refuses an upload that the store has no room for (max_store_bytes, min_free_bytes).
  absl::Status CheckRoom(int64_t job_bytes);

  JobServiceOptions options_;
  std::string runner_;
  std::unique_ptr<render::SharedRenderer> renderer_;
  std::string scratch_dir_;  // data_dir/scratch: RunEnvironment::scratch_dir.
  std::shared_ptr<JobStore> store_;
  std::shared_ptr<BlobStore> blobs_;
  std::mutex store_mutex_;        // Orders store writes of records (never taken with mutex_ held).
  std::mutex render_mutex_;       // Guards render_slots_.
  core::FairSlots render_slots_;  // Pictures being drawn, max_renders of them.
  std::unique_ptr<VolumePictures> volume_pictures_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;  // Any job changed (watchers).
  std::condition_variable work_available_;   // A job may have been queued, or shutdown began.
  mutable std::map<std::string, std::shared_ptr<Entry>> jobs_;
  uint64_t work_signal_ = 0;  // Bumped whenever a job may have been queued (mutex_).
  uint64_t changes_ = 0;      // Bumped with every change watchers may see (mutex_).
  std::vector<std::thread> workers_;
  std::thread sync_thread_;
  std::thread sweep_thread_;            // With retain or max_store_bytes.
  std::condition_variable sweep_wake_;  // Shutdown (mutex_).
  std::atomic<bool> sync_stop_{false};
  std::atomic<bool> store_reachable_{true};
  std::atomic<bool> claims_failing_{false};
  // Set once a tile of another server's job could not be read from this server's blob store: it
  // takes no more tiles (each would only wait out its lease).
  std::atomic<bool> tiles_unreadable_{false};
  int64_t synced_seq_ = 0;  // The store's change number this service has seen (sync thread).
  bool shutting_down_ = false;
  struct HeldInput {
    std::shared_ptr<DecodedInput> input;
    int64_t points = 0;
  };
  std::map<std::string, HeldInput> decoded_;  // Queued jobs' decoded inputs by id (mutex_).
  int64_t decoded_points_ = 0;                // Their points (mutex_).
  std::map<std::string, Usage> pending_;      // Submissions being stored, by owner (mutex_).
  std::vector<TileTask> held_tiles_;          // Tiles this service runs now (mutex_).
};

}  // namespace lsqsurf::jobs
