// worker/jobs/job_service_options.h — what the job service and its parts are told: the
// service's options and limits, who submits, what an owner's jobs hold, a drawn picture.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include "worker/jobs/job.h"
#include "worker/jobs/job_events.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"

namespace lsqsurf::jobs {

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
  // Tests of a mixed rolling update only: the tile format this service publishes and claims tiles
  // in, as a server of another build would; 0: its own (pu::kTileFormat).
  int tile_format = 0;
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

// What an owner's jobs hold now.
struct JobUsage {
  int active_jobs = 0;       // Queued or running.
  int64_t stored_bytes = 0;  // Uploads and results.
};

// The one answer to "may `who` see this job": theirs, or they see all.
inline bool MayView(const Submitter& who, const JobRecord& record) { return who.sees_all || record.owner == who.owner; }

}  // namespace lsqsurf::jobs
