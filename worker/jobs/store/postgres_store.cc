#include "worker/jobs/store/postgres_store.h"

#include <libpq-fe.h>
#include <poll.h>

#include <thread>

#include "worker/core/strings.h"
#include "worker/jobs/store/job_rows.h"

namespace lsqsurf::jobs {
namespace {

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Schema versions in order; a database at version n gets migrations n+1 onwards, each in the
// transaction that records it. Never edit one that has shipped: add the next.
const char* const kMigrations[] = {
    // 1: jobs, removals, the change counter and its triggers, blobs.
    R"sql(
CREATE TABLE jobs (
  id TEXT PRIMARY KEY, method TEXT NOT NULL, parameters TEXT NOT NULL DEFAULT '',
  mesh_bits INTEGER NOT NULL DEFAULT 0, state INTEGER NOT NULL, stage TEXT NOT NULL DEFAULT '',
  attempts INTEGER NOT NULL DEFAULT 0, error TEXT NOT NULL DEFAULT '', created_ms BIGINT NOT NULL,
  updated_ms BIGINT NOT NULL, input_points BIGINT NOT NULL DEFAULT 0, input_bytes BIGINT NOT NULL DEFAULT 0,
  statistics TEXT NOT NULL DEFAULT '', results TEXT NOT NULL DEFAULT '', preview TEXT NOT NULL DEFAULT '',
  preview_color TEXT NOT NULL DEFAULT '', interruptions INTEGER NOT NULL DEFAULT 0,
  progress DOUBLE PRECISION NOT NULL DEFAULT 0, runner TEXT NOT NULL DEFAULT '',
  cancel_requested INTEGER NOT NULL DEFAULT 0, seq BIGINT NOT NULL DEFAULT 0,
  lease_expires_ms BIGINT NOT NULL DEFAULT 0);
CREATE INDEX jobs_queue ON jobs (created_ms, id) WHERE state = {queued};
CREATE INDEX jobs_running ON jobs (runner) WHERE state = {running};
CREATE INDEX jobs_by_seq ON jobs (seq);
CREATE TABLE job_removals (id TEXT PRIMARY KEY, seq BIGINT NOT NULL);
CREATE INDEX job_removals_by_seq ON job_removals (seq);
CREATE TABLE job_counter (seq BIGINT NOT NULL);
INSERT INTO job_counter VALUES (0);
CREATE FUNCTION lsqsurf_now_ms() RETURNS BIGINT LANGUAGE sql VOLATILE
  AS $$ SELECT (extract(epoch FROM clock_timestamp()) * 1000)::BIGINT $$;
-- The counter row stays locked until the writer commits: change numbers follow commit order.
CREATE FUNCTION lsqsurf_next_seq() RETURNS BIGINT LANGUAGE sql VOLATILE
  AS $$ UPDATE job_counter SET seq = seq + 1 RETURNING seq $$;
CREATE FUNCTION lsqsurf_job_written() RETURNS trigger LANGUAGE plpgsql
  AS $$ BEGIN NEW.seq := lsqsurf_next_seq(); RETURN NEW; END $$;
CREATE FUNCTION lsqsurf_job_removed() RETURNS trigger LANGUAGE plpgsql AS $$ BEGIN
  INSERT INTO job_removals VALUES (OLD.id, lsqsurf_next_seq()) ON CONFLICT (id) DO UPDATE SET seq = EXCLUDED.seq;
  RETURN OLD; END $$;
CREATE FUNCTION lsqsurf_notify() RETURNS trigger LANGUAGE plpgsql
  AS $$ BEGIN PERFORM pg_notify('lsqsurf_jobs', ''); RETURN NULL; END $$;
CREATE TRIGGER jobs_inserted BEFORE INSERT ON jobs FOR EACH ROW EXECUTE FUNCTION lsqsurf_job_written();
-- A lease renewal alone is not a change anyone follows.
CREATE TRIGGER jobs_updated BEFORE UPDATE ON jobs FOR EACH ROW
  WHEN (OLD.lease_expires_ms = NEW.lease_expires_ms OR OLD.state <> NEW.state)
  EXECUTE FUNCTION lsqsurf_job_written();
CREATE TRIGGER jobs_removed AFTER DELETE ON jobs FOR EACH ROW EXECUTE FUNCTION lsqsurf_job_removed();
CREATE TRIGGER jobs_notify_written AFTER INSERT OR DELETE ON jobs FOR EACH STATEMENT EXECUTE FUNCTION lsqsurf_notify();
CREATE TRIGGER jobs_notify_updated AFTER UPDATE ON jobs FOR EACH ROW
  WHEN (OLD.lease_expires_ms = NEW.lease_expires_ms OR OLD.state <> NEW.state)
  EXECUTE FUNCTION lsqsurf_notify();
CREATE TABLE blobs (job_id TEXT NOT NULL, name TEXT NOT NULL, generation BIGSERIAL UNIQUE,
  size BIGINT NOT NULL, chunks INTEGER NOT NULL, PRIMARY KEY (job_id, name));
CREATE TABLE blob_chunks (generation BIGINT NOT NULL, chunk INTEGER NOT NULL, data BYTEA NOT NULL,
  PRIMARY KEY (generation, chunk));
)sql",
    // 2: owners (token names) and stored sizes, for isolation, quotas and retention.
    R"sql(
ALTER TABLE jobs ADD COLUMN owner TEXT NOT NULL DEFAULT '';
ALTER TABLE jobs ADD COLUMN stored_bytes BIGINT NOT NULL DEFAULT 0;
UPDATE jobs SET stored_bytes = input_bytes;
)sql",
    // 3: the owner's stored-bytes quota that a job's results are held to while it runs.
    R"sql(
ALTER TABLE jobs ADD COLUMN quota_bytes BIGINT NOT NULL DEFAULT 0;
)sql",
    // 4: tiles of jobs spread over the servers (state 0 queued, 1 running, 2 done).
    R"sql(
CREATE TABLE job_tiles (job_id TEXT NOT NULL, tile BIGINT NOT NULL, state INTEGER NOT NULL,
  runner TEXT NOT NULL, lease_expires_ms BIGINT NOT NULL, attempts INTEGER NOT NULL, PRIMARY KEY (job_id, tile));
CREATE INDEX job_tiles_open ON job_tiles (job_id, tile) WHERE state < 2;
)sql",
    // 5: the format of a tile's plan and part (pu::kTileFormat): servers claim only their own.
    R"sql(
ALTER TABLE job_tiles ADD COLUMN build INTEGER NOT NULL DEFAULT 0;
)sql",
    // 6: the settings servers agree on (Agree).
    R"sql(
CREATE TABLE settings (key TEXT PRIMARY KEY, value TEXT NOT NULL);
)sql",
    // 7: the spec format of each job (SpecTables::format): servers claim only jobs they can read.
    R"sql(
ALTER TABLE jobs ADD COLUMN spec_format INTEGER NOT NULL DEFAULT 0;
)sql",
    // 8: child jobs (a tile is a job: JobRecord::parent) in place of the tiles' own table.
    R"sql(
ALTER TABLE jobs ADD COLUMN parent TEXT NOT NULL DEFAULT '';
ALTER TABLE jobs ADD COLUMN child_index BIGINT NOT NULL DEFAULT 0;
CREATE INDEX jobs_children ON jobs (parent) WHERE parent <> '';
DROP TABLE job_tiles;
)sql",
};
constexpr int kSchemaVersion = sizeof(kMigrations) / sizeof(kMigrations[0]);

// Key of the advisory lock that serializes migrations between servers starting together.
constexpr char kMigrationLock[] = "7202614143";

// Every column but seq, which the database assigns.
const std::string& InsertColumns() {
  static const auto* list = new std::string(rows::ColumnList().substr(0, rows::ColumnList().rfind(", seq")));
  return *list;
}

std::vector<pg::Param> Params(const std::vector<std::string>& values) { return {values.begin(), values.end()}; }

}  // namespace

absl::Status MigratePostgres(pg::Pool& pool) {
  return pool.Transaction([](pg_conn* conn) -> absl::Status {
    for (const std::string& sql :
         {core::StrCat("SELECT pg_advisory_xact_lock(", kMigrationLock, ")"),
          std::string("CREATE TABLE IF NOT EXISTS lsqsurf_schema (version INTEGER NOT NULL)")}) {
      if (auto r = pg::Exec(conn, sql); !r.ok()) return r.status();
    }
    auto current = pg::Exec(conn, "SELECT COALESCE(MAX(version), 0) FROM lsqsurf_schema");
    if (!current.ok()) return current.status();
    const int version = static_cast<int>(rows::ToInt(current->rows.front().front()));
    if (version > kSchemaVersion) {
      return absl::FailedPreconditionError(core::StrCat("the database has schema version ", version,
                                                        ", newer than this server's ", kSchemaVersion,
                                                        "; upgrade the server"));
    }
    for (int v = version + 1; v <= kSchemaVersion; ++v) {
      if (auto r = pg::Exec(conn, rows::WithStates(kMigrations[v - 1])); !r.ok()) {
        return absl::UnavailableError(core::StrCat("schema migration ", v, " failed: ", r.status().message()));
      }
      if (auto r = pg::Exec(conn, "DELETE FROM lsqsurf_schema"); !r.ok()) return r.status();
      if (auto r = pg::Exec(conn, "INSERT INTO lsqsurf_schema VALUES ($1)", {std::to_string(v)}); !r.ok())
        return r.status();
    }
    return absl::OkStatus();
  });
}

absl::StatusOr<std::unique_ptr<PostgresJobStore>> PostgresJobStore::Open(const std::string& url, SpecTables tables,
                                                                         int connections) {
  auto pool = pg::Pool::Open(url, connections);
  if (!pool.ok()) return pool.status();
  if (absl::Status s = MigratePostgres(**pool); !s.ok()) return s;
  std::unique_ptr<PostgresJobStore> store(new PostgresJobStore(*std::move(pool), std::move(tables)));
  std::lock_guard lock(store->listen_mutex_);
  if (absl::Status s = store->Listen(); !s.ok()) return s;
  return store;
}

PostgresJobStore::~PostgresJobStore() { pg::Close(listener_); }

absl::Status PostgresJobStore::Listen() {
  pg::Close(listener_);
  listener_ = nullptr;
  auto conn = pg::Connect(pool_->url());
  if (!conn.ok()) return conn.status();
  listener_ = *conn;
  return pg::Exec(listener_, "LISTEN lsqsurf_jobs").status();
}

absl::StatusOr<std::string> PostgresJobStore::Agree(const std::string& key, const std::string& value) {
  // Two statements: the second one's snapshot sees a row a concurrent first caller committed
  // while this insert waited on it (the insert then does nothing).
  auto inserted =
      pool_->Exec("INSERT INTO settings (key, value) VALUES ($1, $2) ON CONFLICT (key) DO NOTHING", {key, value});
  if (!inserted.ok()) return inserted.status();
  auto kept = pool_->Exec("SELECT value FROM settings WHERE key = $1", {key});
  if (!kept.ok()) return kept.status();
  if (kept->rows.empty()) return absl::UnavailableError(core::StrCat("the setting '", key, "' was not kept"));
  return kept->rows.front().front();
}

void PostgresJobStore::WaitForOthers(std::chrono::milliseconds timeout) {
  std::lock_guard lock(listen_mutex_);
  if (listener_ == nullptr || PQstatus(listener_) != CONNECTION_OK) {
    // The database went away: try again after the timeout, polling meanwhile is all there is.
    std::this_thread::sleep_for(timeout);
    (void)Listen();
    return;
  }
  const auto drain = [&] {
    bool any = false;
    while (PGnotify* n = PQnotifies(listener_)) {
      PQfreemem(n);
      any = true;
    }
    return any;
  };
  if (PQconsumeInput(listener_) == 1 && drain()) return;
  pollfd fd{PQsocket(listener_), POLLIN, 0};
  if (poll(&fd, 1, static_cast<int>(timeout.count())) > 0) {
    if (PQconsumeInput(listener_) != 1) return;  // Broken: the next call reconnects.
    drain();
  }
}

absl::StatusOr<std::vector<JobRecord>> PostgresJobStore::QueryJobs(const std::string& where,
                                                                   const std::vector<pg::Param>& params) {
  auto found = pool_->Exec(core::StrCat("SELECT ", rows::ColumnList(), " FROM jobs ", where), params);
  if (!found.ok()) return found.status();
  std::vector<JobRecord> out;
  out.reserve(found->rows.size());
  for (const auto& row : found->rows) out.push_back(rows::FromColumns(row, tables_));
  return out;
}

absl::Status PostgresJobStore::Insert(const JobRecord& record) {
  std::string placeholders;
  for (int i = 1; i < rows::kColumnCount; ++i) core::StrAppend(&placeholders, i > 1 ? ", $" : "$", i);
  return pool_
      ->Exec(core::StrCat("INSERT INTO jobs (", InsertColumns(), ") VALUES (", placeholders, ")"),
             Params(rows::JobColumns(rows::WithFormat(record, tables_.format))))
      .status();
}

absl::StatusOr<std::optional<JobRecord>> PostgresJobStore::Claim(const std::string& runner,
                                                                 std::chrono::milliseconds lease,
                                                                 const ClaimScope& scope) {
  auto claimed = pool_->Exec(
      core::StrCat(
          rows::WithStates("UPDATE jobs SET state = {running}, stage = 'starting', progress = 0, attempts = "
                           "attempts + 1, cancel_requested = 0, runner = $1, lease_expires_ms = "
                           "lsqsurf_now_ms() + $2, updated_ms = $3 WHERE id = (SELECT id FROM jobs WHERE "
                           "state = {queued} AND ((parent = '' AND $5 = '' AND spec_format <= $4) OR (parent <> '' "
                           "AND spec_format = $6::integer AND ($5 = '' OR parent = $5) AND parent IN (SELECT p.id "
                           "FROM jobs p WHERE p.state = {running}))) ORDER BY parent = '', created_ms, child_index, "
                           "id LIMIT 1 FOR UPDATE SKIP LOCKED) RETURNING "),
          rows::ColumnList()),
      {runner, std::to_string(lease.count()), std::to_string(NowMs()), std::to_string(tables_.format), scope.parent,
       std::to_string(scope.child_format)});
  if (!claimed.ok()) return claimed.status();
  if (claimed->rows.empty()) return std::optional<JobRecord>();
  return std::optional<JobRecord>(rows::FromColumns(claimed->rows.front(), tables_));
}

namespace {
// Writes a held job's record on `conn` if `held_by` still runs it; returns the change number.
absl::StatusOr<int64_t> WriteHeldOn(pg_conn* conn, const JobRecord& record, const std::string& held_by) {
  std::vector<std::string> values = rows::HeldColumns(record);
  values.push_back(held_by);
  auto r = pg::Exec(conn,
                    core::StrCat("UPDATE jobs SET ", rows::HeldAssignments('$'),
                                 rows::WithStates(" WHERE id = $1 AND state = {running} AND runner = $"), values.size(),
                                 " RETURNING seq"),
                    Params(values));
  if (!r.ok()) return r.status();
  if (r->rows.empty()) return absl::AbortedError(core::StrCat("job ", record.id, " is not held by ", held_by));
  return rows::ToInt(r->rows.front().front());
}
}  // namespace

absl::StatusOr<int64_t> PostgresJobStore::WriteHeld(const JobRecord& record) {
  auto conn = pool_->Acquire();
  if (!conn.ok()) return conn.status();
  return WriteHeldOn(conn->get(), record, record.runner);
}

absl::StatusOr<std::vector<std::pair<std::string, bool>>> PostgresJobStore::Renew(const std::string& runner,
                                                                                  const std::vector<std::string>& ids,
                                                                                  std::chrono::milliseconds lease) {
  if (ids.empty()) return std::vector<std::pair<std::string, bool>>();
  std::string array;  // A text[] literal; job ids are hexadecimal, nothing to quote.
  for (const std::string& id : ids) core::StrAppend(&array, array.empty() ? "{" : ",", id);
  array += "}";
  auto held = pool_->Exec(
      rows::WithStates("UPDATE jobs SET lease_expires_ms = lsqsurf_now_ms() + $2 WHERE state = {running} AND "
                       "runner = $1 AND id = ANY($3::text[]) RETURNING id, cancel_requested"),
      {runner, std::to_string(lease.count()), array});
  if (!held.ok()) return held.status();
  std::vector<std::pair<std::string, bool>> out;
  for (const auto& row : held->rows) out.emplace_back(row[0], rows::ToInt(row[1]) != 0);
  return out;
}

absl::StatusOr<std::vector<JobRecord>> PostgresJobStore::RecoverLapsed(bool every_running,
                                                                       const std::function<void(JobRecord&)>& recover) {
  std::vector<JobRecord> out;
  absl::Status s = pool_->Transaction([&](pg_conn* conn) -> absl::Status {
    // Rows another server is writing are skipped: their runner is alive. Locking every lapsed
    // row first means this transaction never waits for one while holding the change counter.
    auto lapsed = pg::Exec(
        conn,
        core::StrCat("SELECT ", rows::ColumnList(), rows::WithStates(" FROM jobs WHERE state = {running}"),
                     every_running ? "" : " AND lease_expires_ms <= lsqsurf_now_ms()", " FOR UPDATE SKIP LOCKED"));
    if (!lapsed.ok()) return lapsed.status();
    for (const auto& row : lapsed->rows) {
      JobRecord r = rows::FromColumns(row, tables_);
      const std::string runner = r.runner;
      recover(r);
      auto seq = WriteHeldOn(conn, r, runner);
      if (!seq.ok()) return seq.status();
      r.seq = *seq;
      out.push_back(std::move(r));
    }
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  return out;
}

absl::StatusOr<JobRecord> PostgresJobStore::Cancel(const std::string& id, const std::string& reason) {
  auto changed = pool_->Exec(
      core::StrCat(
          rows::WithStates("UPDATE jobs SET error = CASE WHEN state = {queued} THEN $2 ELSE error END, "
                           "cancel_requested = CASE WHEN state = {running} THEN 1 ELSE cancel_requested END, "
                           "stored_bytes = CASE WHEN state = {queued} THEN input_bytes ELSE stored_bytes END, "
                           "state = CASE WHEN state = {queued} THEN {cancelled} ELSE state END, updated_ms = $3 "
                           "WHERE id = $1 AND state IN ({queued}, {running}) RETURNING "),
          rows::ColumnList()),
      {id, reason, std::to_string(NowMs())});
  if (!changed.ok()) return changed.status();
  if (!changed->rows.empty()) return rows::FromColumns(changed->rows.front(), tables_);
  auto found = Get(id);
  if (!found.ok()) return found.status();
  return AlreadyFinished(*found);
}

absl::Status PostgresJobStore::Remove(const std::string& id) {
  bool removed = false;
  absl::Status s = pool_->Transaction([&](pg_conn* conn) -> absl::Status {
    auto parent = pg::Exec(conn, rows::WithStates("DELETE FROM jobs WHERE id = $1 AND state IN {finished}"), {id});
    if (!parent.ok()) return parent.status();
    removed = parent->affected > 0;
    if (!removed) return absl::OkStatus();
    return pg::Exec(conn, "DELETE FROM jobs WHERE parent = $1", {id}).status();
  });
  if (!s.ok()) return s;
  if (removed) return absl::OkStatus();
  auto found = Get(id);
  if (!found.ok()) return found.status();
  return NotFinished(*found);
}

absl::StatusOr<JobRecord> PostgresJobStore::Get(const std::string& id) {
  auto found = QueryJobs("WHERE id = $1", {id});
  if (!found.ok()) return found.status();
  if (found->empty()) return NoSuchJob(id);
  return std::move(found->front());
}

absl::StatusOr<JobChanges> PostgresJobStore::ChangesSince(int64_t seq) {
  JobChanges out;
  // One snapshot for the three reads, so the number returned covers exactly what was read.
  absl::Status s = pool_->Transaction([&](pg_conn* conn) -> absl::Status {
    if (auto r = pg::Exec(conn, "SET TRANSACTION ISOLATION LEVEL REPEATABLE READ READ ONLY"); !r.ok())
      return r.status();
    const std::string since = std::to_string(seq);
    auto counter = pg::Exec(conn, "SELECT seq FROM job_counter");
    if (!counter.ok()) return counter.status();
    out.seq = rows::ToInt(counter->rows.front().front());
    auto changed =
        pg::Exec(conn, core::StrCat("SELECT ", rows::ColumnList(), " FROM jobs WHERE seq > $1 ORDER BY seq"), {since});
    if (!changed.ok()) return changed.status();
    for (const auto& row : changed->rows) out.changed.push_back(rows::FromColumns(row, tables_));
    auto removed = pg::Exec(conn, "SELECT id FROM job_removals WHERE seq > $1 ORDER BY seq", {since});
    if (!removed.ok()) return removed.status();
    for (auto& row : removed->rows) out.removed.push_back(std::move(row[0]));
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  return out;
}

namespace {

class ChunkReader final : public BlobReader {
 public:
  ChunkReader(std::shared_ptr<pg::Pool> pool, std::string generation, int64_t size, int chunks)
      : pool_(std::move(pool)), generation_(std::move(generation)), size_(size), chunks_(chunks) {}
  int64_t size() const override { return size_; }
  absl::StatusOr<std::string> Next(size_t max_bytes) override {
    if (offset_ == buffer_.size()) {
      if (next_chunk_ >= chunks_) return std::string();
      auto r = pool_->Exec("SELECT data FROM blob_chunks WHERE generation = $1 AND chunk = $2",
                           {generation_, std::to_string(next_chunk_)}, /*binary_results=*/true);
      if (!r.ok()) return r.status();
      if (r->rows.empty()) return absl::UnavailableError("the stored data was replaced or removed while being read");
      buffer_ = std::move(r->rows.front().front());
      offset_ = 0;
      ++next_chunk_;
    }
    const size_t n = std::min(max_bytes, buffer_.size() - offset_);
    std::string out = buffer_.substr(offset_, n);
    offset_ += n;
    return out;
  }

 private:
  std::shared_ptr<pg::Pool> pool_;
  std::string generation_;
  int64_t size_;
  int chunks_;
  int next_chunk_ = 0;
  std::string buffer_;
  size_t offset_ = 0;
};

}  // namespace

absl::Status PostgresBlobStore::Put(const std::string& job_id, std::string_view name, std::string_view bytes) {
  const int chunks = static_cast<int>((bytes.size() + kChunkBytes - 1) / kChunkBytes);
  absl::Status s = pool_->Transaction([&](pg_conn* conn) -> absl::Status {
    // The old version's chunks go with the same commit that makes the new one visible.
    auto old =
        pg::Exec(conn, "SELECT generation FROM blobs WHERE job_id = $1 AND name = $2 FOR UPDATE", {job_id, name});
    if (!old.ok()) return old.status();
    auto made = pg::Exec(conn,
                         "INSERT INTO blobs (job_id, name, size, chunks) VALUES ($1, $2, $3, $4) "
                         "ON CONFLICT (job_id, name) DO UPDATE SET generation = nextval('blobs_generation_seq'), "
                         "size = EXCLUDED.size, chunks = EXCLUDED.chunks RETURNING generation",
                         {job_id, name, std::to_string(bytes.size()), std::to_string(chunks)});
    if (!made.ok()) return made.status();
    const std::string& generation = made->rows.front().front();
    for (int i = 0; i < chunks; ++i) {
      const std::string_view piece = bytes.substr(static_cast<size_t>(i) * kChunkBytes, kChunkBytes);
      auto r = pg::Exec(conn, "INSERT INTO blob_chunks (generation, chunk, data) VALUES ($1, $2, $3)",
                        {generation, std::to_string(i), pg::Param::Bytes(piece)});
      if (!r.ok()) return r.status();
    }
    if (!old->rows.empty()) {
      auto r = pg::Exec(conn, "DELETE FROM blob_chunks WHERE generation = $1", {old->rows.front().front()});
      if (!r.ok()) return r.status();
    }
    return absl::OkStatus();
  });
  if (!s.ok()) return absl::UnavailableError(core::StrCat("cannot store ", name, ": ", s.message()));
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<BlobReader>> PostgresBlobStore::Open(const std::string& job_id,
                                                                    std::string_view name) const {
  auto found =
      pool_->Exec("SELECT generation, size, chunks FROM blobs WHERE job_id = $1 AND name = $2", {job_id, name});
  if (!found.ok()) return found.status();
  if (found->rows.empty()) return NoSuchBlob(job_id, name);
  const auto& row = found->rows.front();
  return std::make_unique<ChunkReader>(pool_, row[0], rows::ToInt(row[1]), static_cast<int>(rows::ToInt(row[2])));
}

bool PostgresBlobStore::Exists(const std::string& job_id, std::string_view name) const {
  auto found = pool_->Exec("SELECT 1 FROM blobs WHERE job_id = $1 AND name = $2", {job_id, name});
  return found.ok() && !found->rows.empty();
}

absl::Status PostgresBlobStore::Remove(const std::string& job_id, std::string_view name) {
  return pool_->Transaction([&](pg_conn* conn) -> absl::Status {
    auto gone =
        pg::Exec(conn, "DELETE FROM blobs WHERE job_id = $1 AND name = $2 RETURNING generation", {job_id, name});
    if (!gone.ok()) return gone.status();
    for (const auto& row : gone->rows) {
      if (auto r = pg::Exec(conn, "DELETE FROM blob_chunks WHERE generation = $1", {row[0]}); !r.ok())
        return r.status();
    }
    return absl::OkStatus();
  });
}

absl::Status PostgresBlobStore::RemoveJob(const std::string& job_id) {
  absl::Status s = pool_->Transaction([&](pg_conn* conn) -> absl::Status {
    for (const char* sql : {"DELETE FROM blob_chunks WHERE generation IN (SELECT generation FROM blobs WHERE "
                            "job_id = $1)",
                            "DELETE FROM blobs WHERE job_id = $1"}) {
      if (auto r = pg::Exec(conn, sql, {job_id}); !r.ok()) return r.status();
    }
    return absl::OkStatus();
  });
  if (!s.ok())
    return absl::UnavailableError(core::StrCat("cannot remove the blobs of job ", job_id, ": ", s.message()));
  return absl::OkStatus();
}

}  // namespace lsqsurf::jobs
