// worker/jobs/job_table.h — the job records a service holds in memory, and the decoded inputs
// kept for queued jobs. The table is what the service's parts (admission, runner, replication,
// retention, pictures) share: they read and change records only through it, so that what
// watchers see is always what the store has.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/store/job_store.h"

namespace lsqsurf::jobs {

// One job as this service knows it.
struct JobEntry {
  JobRecord record;   // Guarded by the table's lock.
  bool held = false;  // This service runs the job; guarded by the table's lock.
  std::atomic<bool> cancel_requested{false};
  std::atomic<bool> interrupted{false};  // Shutdown: re-queue rather than cancel.
  std::atomic<bool> lost{false};         // The lease lapsed: another service may run it now.
  // This run's writes to the store under way, and the newest change that arrived meanwhile
  // looking like another service's (it may be one of them, stored but not yet recorded here);
  // guarded by the table's lock.
  int writes_in_flight = 0;
  int64_t seq_seen_while_writing = 0;
  bool removed_elsewhere = false;  // Deleted through another service while held; table's lock.
};

using JobEntries = std::map<std::string, std::shared_ptr<JobEntry>>;

// Queued jobs' inputs as Submit decoded them, kept for their runs while they hold at most
// `max_points` points together (else the run decodes the stored upload again). Thread-safe.
class DecodedInputs {
 public:
  explicit DecodedInputs(int64_t max_points) : max_points_(max_points) {}
  // Keeps `input` for job `id` if the budget allows; false when it does not.
  bool Keep(const std::string& id, std::shared_ptr<DecodedInput> input, int64_t points);
  // Takes a job's input out of the budget; null if none is kept.
  std::shared_ptr<DecodedInput> Take(const std::string& id);

 private:
  struct Held {
    std::shared_ptr<DecodedInput> input;
    int64_t points = 0;
  };
  const int64_t max_points_;
  std::mutex mutex_;
  std::map<std::string, Held> held_;
  int64_t points_ = 0;
};

// Thread-safe. Reads (Get, List, the waits) never wait on the store: records change in memory
// after the store has them (Update), outside the table's lock for the store's part.
class JobTable {
 public:
  JobTable(std::shared_ptr<JobStore> store, DecodedInputs& decoded) : store_(std::move(store)), decoded_(decoded) {}

  // The job's entry, read from a shared store when this service has not seen it yet; null if none.
  std::shared_ptr<JobEntry> Find(const std::string& id) const;
  // A copy of the job's record. Errors: kNotFound.
  absl::StatusOr<JobRecord> Get(const std::string& id) const;
  JobRecord Snapshot(const JobEntry& entry) const;
  std::vector<JobRecord> List() const;  // Newest first; no child jobs (JobRecord::parent).
  // Copies of the records of `parent`'s child jobs this service knows of, by id, those `keep`
  // accepts (all when null), at most `at_most`; looked up in an index, not by scanning every job
  // (a tiled build asks at every look).
  std::vector<JobRecord> Children(const std::string& parent,
                                  const std::function<bool(const JobRecord&)>& keep = nullptr,
                                  size_t at_most = SIZE_MAX) const;
  // Runs `f` with the entries under the table's lock (AdoptLocked and EraseLocked may be called
  // from it); returns what `f` returns. `f` must not call the store nor the table's other methods.
  template <typename F>
  auto Locked(F&& f) const {
    std::lock_guard lock(mutex_);
    return f(jobs_);
  }
  // Takes a record read from the store unless this service's copy is as new; returns the entry
  // (made if missing). Only within Locked.
  std::shared_ptr<JobEntry> AdoptLocked(JobRecord record) const;
  // Forgets a job (its decoded input too). Only within Locked.
  void EraseLocked(const std::string& id) const;

  // Applies `change` to the record and wakes watchers; with `persist`, stores the changed record
  // first (a held job's), so that what watchers see is in the store already.
  void Update(const std::shared_ptr<JobEntry>& entry, const std::function<void(JobRecord&)>& change,
              bool persist = true);
  // A job this service claimed from the store: held from now on, its cancellation and the
  // shutdown's interruption taken from the record and the table.
  std::shared_ptr<JobEntry> Hold(JobRecord claimed);
  // The run of a held job ended: it is no longer held, and what the store has replaces it where
  // the run was lost or the job removed elsewhere.
  void Release(const std::shared_ptr<JobEntry>& entry);
  // Cancels in the store and here. Errors: those of JobStore::Cancel.
  absl::StatusOr<JobRecord> Cancel(const std::string& id);
  // The run's lease lapsed: it stops, logged once.
  static void MarkLost(JobEntry& entry, const std::string& id);

  void NotifyChanged();  // Counts a change and wakes the watchers.
  uint64_t WaitForAnyChange(uint64_t seen, std::chrono::milliseconds timeout) const;
  absl::StatusOr<JobRecord> WaitForChange(const std::string& id, uint64_t seen_version,
                                          std::chrono::milliseconds timeout) const;
  // Refuses nothing by itself; marks the held jobs interrupted and wakes every waiter. False
  // when it had begun before.
  bool BeginShutdown();
  bool shutting_down() const;

 private:
  // Writes a held job's record; its change number, or 0 when the write failed.
  int64_t Persist(const std::shared_ptr<JobEntry>& entry, const JobRecord& record);

  std::shared_ptr<JobStore> store_;
  DecodedInputs& decoded_;
  std::mutex store_mutex_;  // Orders store writes of records (never taken with mutex_ held).
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  mutable JobEntries jobs_;
  // The ids of each parent's child jobs among jobs_ (a job's parent never changes); mutex_.
  mutable std::map<std::string, std::set<std::string>> children_;
  uint64_t changes_ = 0;  // Bumped with every change watchers may see (mutex_).
  bool shutting_down_ = false;
};

}  // namespace lsqsurf::jobs
