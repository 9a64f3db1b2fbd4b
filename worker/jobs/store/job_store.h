// worker/jobs/store/job_store.h — durable job records, and who runs which job.
//
// The store is where servers agree on the jobs: a job is claimed from it by one server at a
// time, under a lease that server renews; a server that dies stops renewing, and another one
// (or the same one restarted) recovers the job. The embedded SQLite store serves one server;
// the PostgreSQL store (postgres_store.h) lets several share the jobs. Both keep the contract
// tested in tests/jobs/job_store_test.cc.
//
// Parameters and view options are stored in the text form their descriptor tables define
// ("name=value;..."), so a stored job reads back with every field its method knows.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job.h"
#include "worker/jobs/store/spec_tables.h"

struct sqlite3;

namespace lsqsurf::jobs {

// What changed in a store since a change number: the jobs written since (newest state) and
// the ids removed since.
struct JobChanges {
  std::vector<JobRecord> changed;
  std::vector<std::string> removed;
  int64_t seq = 0;  // Give this to the next call.
};

// Which queued jobs a claim may take.
struct ClaimScope {
  // Child jobs (JobRecord::parent) of exactly this spec format, of running parents only, come
  // before any other job; 0: none.
  int child_format = 0;
  // Only the children of this job (a parent's run making its own parts); "": any job.
  std::string parent;
};

// Implementations are thread-safe; every write is durable when it returns. Every write gives
// the job a new change number (JobRecord::seq), larger than any before it.
class JobStore {
 public:
  virtual ~JobStore() = default;
  // Whether other servers write to this store too (their jobs appear; leases matter).
  virtual bool shared() const = 0;

  // Stores a new job as the record says. Errors: kAlreadyExists, kUnavailable.
  virtual absl::Status Insert(const JobRecord& record) = 0;
  // Takes the oldest queued job within `scope` for `runner`: it becomes running, with stage
  // "starting", one more attempt and a lease of `lease`. A job a user submitted is claimed only by
  // a store of its spec format or a newer one. nullopt when none is queued. Errors: kUnavailable.
  virtual absl::StatusOr<std::optional<JobRecord>> Claim(const std::string& runner, std::chrono::milliseconds lease,
                                                         const ClaimScope& scope = {}) = 0;
  // Replaces the record of a job that `record.runner` holds (running under that runner). A
  // runner whose lease lapsed has no say any more. Returns the new change number. Errors:
  // kAborted (not held by that runner), kUnavailable.
  virtual absl::StatusOr<int64_t> WriteHeld(const JobRecord& record) = 0;
  // Extends by `lease` the leases of those of `ids` that `runner` holds; returns the ids still
  // held, with whether a cancellation was asked for. Errors: kUnavailable.
  virtual absl::StatusOr<std::vector<std::pair<std::string, bool>>> Renew(const std::string& runner,
                                                                          const std::vector<std::string>& ids,
                                                                          std::chrono::milliseconds lease) = 0;
  // Running jobs whose lease has lapsed (every running job with `every_running`, for a store
  // nobody else writes to) are handed to `recover`, which sets their new state; the changed
  // records are returned. Errors: kUnavailable.
  virtual absl::StatusOr<std::vector<JobRecord>> RecoverLapsed(bool every_running,
                                                               const std::function<void(JobRecord&)>& recover) = 0;
  // A queued job becomes cancelled with `reason`; a running one is flagged (its runner stops
  // it). Returns the record after that. Errors: kNotFound, kFailedPrecondition (finished).
  virtual absl::StatusOr<JobRecord> Cancel(const std::string& id, const std::string& reason) = 0;
  // Removes a finished job, and its child jobs in any state. Errors: kNotFound,
  // kFailedPrecondition (not finished).
  virtual absl::Status Remove(const std::string& id) = 0;

  // Errors: kNotFound, kUnavailable.
  virtual absl::StatusOr<JobRecord> Get(const std::string& id) = 0;
  // What changed after change number `seq` (0: every job there is), in the order of change. A
  // job whose stored spec no longer decodes (here and in Get, Claim) comes back failed, saying why.
  virtual absl::StatusOr<JobChanges> ChangesSince(int64_t seq) = 0;
  // Returns when another server may have written, or after `timeout`.
  virtual void WaitForOthers(std::chrono::milliseconds timeout) = 0;
  // The value kept under `key`, keeping `value` there first where there is none: the first
  // caller decides, and every caller after it, on any server, gets that value. Errors: kUnavailable.
  virtual absl::StatusOr<std::string> Agree(const std::string& key, const std::string& value) = 0;
};

// The messages both stores give for a job that is not there or in the wrong state.
absl::Status NoSuchJob(const std::string& id);
absl::Status AlreadyFinished(const JobRecord& record);
absl::Status NotFinished(const JobRecord& record);

// One database file for one server: a jobs table and a table of removals (WAL journal,
// synchronous FULL, every write its own transaction). Databases of earlier versions are migrated
// on open (columns added, view options renamed; PRAGMA user_version holds the schema version).
// Calls are serialized by an internal mutex. Not shared: one server opens it at a time.
class SqliteJobStore final : public JobStore {
 public:
  // Opens (creating if needed) the database at `path`; stored specs are read with `tables`.
  // Errors: kUnavailable with SQLite's reason.
  static absl::StatusOr<std::unique_ptr<SqliteJobStore>> Open(const std::string& path, SpecTables tables);
  ~SqliteJobStore() override;

  bool shared() const override { return false; }
  absl::Status Insert(const JobRecord& record) override;
  absl::StatusOr<std::optional<JobRecord>> Claim(const std::string& runner, std::chrono::milliseconds lease,
                                                 const ClaimScope& scope) override;
  absl::StatusOr<int64_t> WriteHeld(const JobRecord& record) override;
  absl::StatusOr<std::vector<std::pair<std::string, bool>>> Renew(const std::string& runner,
                                                                  const std::vector<std::string>& ids,
                                                                  std::chrono::milliseconds lease) override;
  absl::StatusOr<std::vector<JobRecord>> RecoverLapsed(bool every_running,
                                                       const std::function<void(JobRecord&)>& recover) override;
  absl::StatusOr<JobRecord> Cancel(const std::string& id, const std::string& reason) override;
  absl::Status Remove(const std::string& id) override;
  absl::StatusOr<JobRecord> Get(const std::string& id) override;
  absl::StatusOr<JobChanges> ChangesSince(int64_t seq) override;
  void WaitForOthers(std::chrono::milliseconds timeout) override;
  absl::StatusOr<std::string> Agree(const std::string& key, const std::string& value) override;

 private:
  using Row = std::vector<std::string>;
  SqliteJobStore(sqlite3* db, SpecTables tables) : tables_(std::move(tables)), db_(db) {}
  absl::Status Migrate();
  // Runs one statement with text parameters; the rows it returns, as text. mutex_ held.
  absl::StatusOr<std::vector<Row>> Query(const std::string& sql, const std::vector<std::string>& params = {});
  absl::StatusOr<std::vector<JobRecord>> QueryJobs(const std::string& where, const std::vector<std::string>& params);
  // Writes the record over a job that `held_by` runs; kAborted when it does not. mutex_ held.
  absl::StatusOr<int64_t> Replace(const JobRecord& record, const std::string& held_by);
  const SpecTables tables_;
  std::mutex mutex_;
  sqlite3* db_;
  int64_t seq_ = 0;  // The last change number given (mutex_).
};

}  // namespace lsqsurf::jobs
