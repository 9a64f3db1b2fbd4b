// worker/jobs/store/postgres_store.h — jobs and their bytes in PostgreSQL, shared by several servers.
//
// PostgresJobStore keeps the JobStore contract for any number of servers on one database:
//  - a job is claimed with SELECT ... FOR UPDATE SKIP LOCKED, so two servers never take the
//    same one and neither waits for the other;
//  - every write of a job gets its change number from one counter row, taken by a trigger and
//    held to the commit, so change numbers follow commit order and a reader that has seen
//    number n has seen every change up to n;
//  - writes notify the channel "lsqsurf_jobs", which WaitForOthers listens to;
//  - leases are measured on the database's clock, so servers' clocks need not agree.
// The schema is versioned (table lsqsurf_schema) and migrated at open, under an advisory lock
// so servers starting together do it once.
//
// PostgresBlobStore keeps blobs in the same database, in chunks of 1 MiB: every server reaches
// them and no shared file system is needed. Limits: a blob must fit the database's disk, and a
// read keeps one chunk in memory; a blob replaced or removed while being read makes that read
// fail (kUnavailable) rather than mix two versions.
#pragma once

#include <memory>
#include <mutex>
#include <string>

#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"
#include "worker/jobs/store/postgres_connection.h"

namespace lsqsurf::jobs {

class PostgresJobStore final : public JobStore {
 public:
  // Connects to `url` (a libpq URI, postgresql://user@host:port/db, or "key=value ..." text),
  // migrates the schema and listens for the others' changes; stored specs are read with `tables`.
  // Errors: kUnavailable.
  static absl::StatusOr<std::unique_ptr<PostgresJobStore>> Open(const std::string& url, SpecTables tables,
                                                                int connections = 8);
  ~PostgresJobStore() override;

  bool shared() const override { return true; }
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

  // The pool, for a blob store on the same database.
  const std::shared_ptr<pg::Pool>& pool() const { return pool_; }

 private:
  PostgresJobStore(std::shared_ptr<pg::Pool> pool, SpecTables tables)
      : pool_(std::move(pool)), tables_(std::move(tables)) {}
  absl::StatusOr<std::vector<JobRecord>> QueryJobs(const std::string& where, const std::vector<pg::Param>& params);
  absl::Status Listen();  // listen_mutex_ held.
  std::shared_ptr<pg::Pool> pool_;
  const SpecTables tables_;
  std::mutex listen_mutex_;
  pg_conn* listener_ = nullptr;  // LISTENs on lsqsurf_jobs; guarded by listen_mutex_.
};

// Applies the schema migrations this build knows to the database (both stores' tables).
absl::Status MigratePostgres(pg::Pool& pool);

class PostgresBlobStore final : public BlobStore {
 public:
  explicit PostgresBlobStore(std::shared_ptr<pg::Pool> pool) : pool_(std::move(pool)) {}

  absl::Status Put(const std::string& job_id, std::string_view name, std::string_view bytes) override;
  absl::StatusOr<std::unique_ptr<BlobReader>> Open(const std::string& job_id, std::string_view name) const override;
  bool Exists(const std::string& job_id, std::string_view name) const override;
  absl::Status Remove(const std::string& job_id, std::string_view name) override;
  absl::Status RemoveJob(const std::string& job_id) override;

  static constexpr size_t kChunkBytes = size_t{1} << 20;

 private:
  std::shared_ptr<pg::Pool> pool_;
};

}  // namespace lsqsurf::jobs
