// worker/jobs/job_replication.h — what a service does for the servers it shares a store with:
// it follows their changes (a notification, else polling every `poll`), passes cancellations on
// to its runs, renews the leases of the jobs it runs (tiles' child jobs too), and recovers the jobs of servers
// whose lease lapsed. With a store of its own only the recovery at start applies.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "worker/jobs/job_service_options.h"
#include "worker/jobs/job_table.h"
#include "worker/jobs/store/blob_store.h"

namespace lsqsurf::jobs {

// The new state of a job whose runner stopped while it ran: cancelled if that was asked for,
// queued again, or failed once such stops add up to `max_attempts` (a tile's child job with a
// reason its build reports, naming the tile).
void RecoverStoppedRun(JobRecord& r, int max_attempts);

// Thread-safe.
class JobReplication {
 public:
  // `wake_workers` is told when another server queued a job.
  JobReplication(const JobServiceOptions& options, std::string runner, JobTable& table, JobStore& store,
                 std::function<void()> wake_workers)
      : options_(options),
        runner_(std::move(runner)),
        table_(table),
        store_(store),
        wake_workers_(std::move(wake_workers)) {}
  ~JobReplication() { Stop(); }

  // A shared store's servers must share their blob store too (each runs jobs whose uploads
  // another took): the first server to start leaves a witness blob and names it in the job
  // store; one that cannot read that blob has a blob store of its own and must not start.
  // Errors: kFailedPrecondition saying so, the stores' own.
  absl::Status CheckBlobsShared(BlobStore& blobs);
  // Takes every job on record into the table (at start). Errors: the store's.
  absl::Status LoadAll();
  // Requeues (or fails, or cancels) the jobs of runners whose lease lapsed; every running job
  // with `every_running`. Errors: the store's.
  absl::Status RecoverLapsed(bool every_running);
  // Shared stores: follows the others on a thread of its own until Stop.
  void Start();
  void Stop();  // Idempotent; call once the runs have ended, whose leases it renews until then.
  // Whether the store answered the last look (always true for a store of its own).
  bool StoreReachable() const { return store_reachable_.load(); }

 private:
  void SyncLoop();
  void SyncChanges();
  void RenewLeases();

  const JobServiceOptions& options_;
  const std::string runner_;
  JobTable& table_;
  JobStore& store_;
  const std::function<void()> wake_workers_;
  int64_t synced_seq_ = 0;  // The store's change number this service has seen (sync thread).
  std::atomic<bool> stop_{false};
  std::atomic<bool> store_reachable_{true};
  std::thread thread_;
};

}  // namespace lsqsurf::jobs
