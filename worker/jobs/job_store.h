// worker/jobs/job_store.h — durable job records.
//
// A narrow interface on purpose: the embedded SQLite store below is the default, and a shared
// store for scale-out (PostgreSQL) is another implementation, not a change to its callers.
// Parameters and view options are stored in the text form their descriptor tables define
// ("name=value;..."), so a stored job reads back with every field its method knows.
#pragma once

#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job.h"

struct sqlite3;

namespace lsqsurf::jobs {

// Implementations are thread-safe; every write is durable when it returns.
class JobStore {
 public:
  virtual ~JobStore() = default;
  virtual absl::Status Put(const JobRecord& record) = 0;  // Insert or replace.
  virtual absl::Status Remove(const std::string& id) = 0;
  // Every job, oldest first. A job whose method no longer exists comes back failed, saying so.
  virtual absl::StatusOr<std::vector<JobRecord>> LoadAll() = 0;
};

// One table, one row per job; every write is its own transaction (WAL journal, synchronous
// FULL). Databases of earlier versions are migrated on open (added columns, renamed view
// options). Thread safety: calls are serialized by an internal mutex.
class SqliteJobStore final : public JobStore {
 public:
  // Opens (creating if needed) the database at `path`. Errors: kUnavailable with SQLite's reason.
  static absl::StatusOr<std::unique_ptr<SqliteJobStore>> Open(const std::string& path);
  ~SqliteJobStore() override;

  absl::Status Put(const JobRecord& record) override;
  absl::Status Remove(const std::string& id) override;
  absl::StatusOr<std::vector<JobRecord>> LoadAll() override;

 private:
  explicit SqliteJobStore(sqlite3* db) : db_(db) {}
  absl::Status Exec(const char* sql);
  bool HasColumn(const char* name);  // Of the jobs table.
  std::mutex mutex_;
  sqlite3* db_;
};

}  // namespace lsqsurf::jobs
