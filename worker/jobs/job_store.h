// worker/jobs/job_store.h — durable job records in an embedded SQLite database.
//
// One table, one row per job; every write is its own transaction (WAL journal, synchronous
// FULL), so a record is on disk before the call returns. Thread safety: all methods are
// serialized by an internal mutex. A narrow interface on purpose: a PostgreSQL implementation
// for scale-out replaces this file, not its callers.
#pragma once

#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job.h"

struct sqlite3;

namespace lsqsurf::jobs {

class JobStore {
 public:
  // Opens (creating if needed) the database at `path`. Errors: kUnavailable with SQLite's reason.
  static absl::StatusOr<std::unique_ptr<JobStore>> Open(const std::string& path);
  ~JobStore();

  absl::Status Put(const JobRecord& record);  // Insert or replace.
  absl::Status Remove(const std::string& id);
  // Every job, oldest first.
  absl::StatusOr<std::vector<JobRecord>> LoadAll();

 private:
  explicit JobStore(sqlite3* db) : db_(db) {}
  absl::Status Exec(const char* sql);
  bool HasColumn(const char* name);  // Of the jobs table.
  std::mutex mutex_;
  sqlite3* db_;
};

}  // namespace lsqsurf::jobs
