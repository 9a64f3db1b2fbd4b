#include "worker/jobs/store/job_store.h"

#include <sqlite3.h>

#include <thread>

#include "worker/core/strings.h"
#include "worker/jobs/store/job_rows.h"

namespace lsqsurf::jobs {
namespace {

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// The schema version this build writes (PRAGMA user_version). 0: the unversioned tables of
// earlier builds; 1: runners, leases, change numbers and the removals table; 2: owners and
// stored sizes; 3: the owner's quota a job's results are held to; 4: tiles; 5: the tiles' format;
// 6: the settings servers agree on (Agree). 7: the spec format of each job. 8: child jobs in
// place of the tiles' table.
constexpr int kSchemaVersion = 8;

}  // namespace

absl::Status NoSuchJob(const std::string& id) { return absl::NotFoundError(core::StrCat("no job with id '", id, "'")); }

absl::Status AlreadyFinished(const JobRecord& r) {
  return absl::FailedPreconditionError(core::StrCat("job ", r.id, " has already ", JobStateName(r.state)));
}

absl::Status NotFinished(const JobRecord& r) {
  return absl::FailedPreconditionError(
      core::StrCat("job ", r.id, " is ", JobStateName(r.state), "; cancel it before deleting it"));
}

const char* JobStateName(JobState state) {
  switch (state) {
    case JobState::kQueued: return "queued";
    case JobState::kRunning: return "running";
    case JobState::kSucceeded: return "succeeded";
    case JobState::kFailed: return "failed";
    case JobState::kCancelled: return "cancelled";
  }
  return "unknown";
}

bool IsTerminal(JobState state) {
  return state == JobState::kSucceeded || state == JobState::kFailed || state == JobState::kCancelled;
}

absl::StatusOr<std::unique_ptr<SqliteJobStore>> SqliteJobStore::Open(const std::string& path, SpecTables tables) {
  sqlite3* db = nullptr;
  if (sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX, nullptr) !=
      SQLITE_OK) {
    std::string msg = db ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::UnavailableError(core::StrCat("cannot open job database ", path, ": ", msg));
  }
  std::unique_ptr<SqliteJobStore> store(new SqliteJobStore(db, std::move(tables)));
  std::lock_guard lock(store->mutex_);
  if (absl::Status s = store->Migrate(); !s.ok()) return s;
  auto last = store->Query(
      "SELECT MAX(COALESCE((SELECT MAX(seq) FROM jobs), 0), "
      "COALESCE((SELECT MAX(seq) FROM job_removals), 0))");
  if (!last.ok()) return last.status();
  store->seq_ = rows::ToInt(last->front().front());
  return store;
}

absl::Status SqliteJobStore::Migrate() {
  // An up-to-date database is opened without a write: a server whose disk filled up must still
  // start, to serve what it stored and let its jobs be deleted.
  auto version = Query("PRAGMA user_version");
  if (!version.ok()) return version.status();
  if (!version->empty() && rows::ToInt(version->front().front()) == kSchemaVersion) {
    for (const char* sql : {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=FULL"}) {
      if (auto r = Query(sql); !r.ok()) return r.status();
    }
    return absl::OkStatus();
  }
  for (const char* sql :
       {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=FULL",
        "CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, method TEXT, "
        "parameters TEXT, mesh_bits INTEGER, state INTEGER, stage TEXT, "
        "attempts INTEGER, error TEXT, created_ms INTEGER, updated_ms INTEGER, "
        "input_points INTEGER, input_bytes INTEGER, statistics TEXT, results TEXT)",
        "CREATE TABLE IF NOT EXISTS job_removals (id TEXT PRIMARY KEY, seq INTEGER)", "DROP TABLE IF EXISTS job_tiles",
        "CREATE TABLE IF NOT EXISTS settings (key TEXT PRIMARY KEY, value TEXT NOT NULL)"}) {
    if (auto r = Query(sql); !r.ok()) return r.status();
  }
  // Databases written by earlier builds lack the later columns; each is added where missing,
  // so a database of any earlier version ends up alike.
  auto present = Query("SELECT name FROM pragma_table_info('jobs')");
  if (!present.ok()) return present.status();
  for (const char* column :
       {"preview TEXT", "preview_color TEXT", "interruptions INTEGER", "progress REAL", "runner TEXT",
        "cancel_requested INTEGER", "seq INTEGER", "lease_expires_ms INTEGER", "owner TEXT NOT NULL DEFAULT ''",
        "stored_bytes INTEGER", "quota_bytes INTEGER NOT NULL DEFAULT 0", "spec_format INTEGER NOT NULL DEFAULT 0",
        "parent TEXT NOT NULL DEFAULT ''", "child_index INTEGER NOT NULL DEFAULT 0"}) {
    const std::string name(column, std::string_view(column).find(' '));
    const bool has = std::any_of(present->begin(), present->end(), [&](const Row& row) { return row[0] == name; });
    if (has) continue;
    if (auto r = Query(core::StrCat("ALTER TABLE jobs ADD COLUMN ", column)); !r.ok()) return r.status();
  }
  // Rows of earlier builds get values where the new columns must have one.
  if (auto r = Query("UPDATE jobs SET runner = COALESCE(runner, ''), cancel_requested = COALESCE(cancel_requested, 0), "
                     "progress = COALESCE(progress, 0), interruptions = COALESCE(interruptions, 0), "
                     "seq = COALESCE(seq, rowid) WHERE seq IS NULL");
      !r.ok()) {
    return r.status();
  }
  if (auto r = Query("UPDATE jobs SET stored_bytes = COALESCE(input_bytes, 0) WHERE stored_bytes IS NULL"); !r.ok()) {
    return r.status();
  }
  for (const char* sql : {"CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state, created_ms, id)",
                          "CREATE INDEX IF NOT EXISTS jobs_by_seq ON jobs (seq)",
                          "CREATE INDEX IF NOT EXISTS jobs_by_parent ON jobs (parent) WHERE parent <> ''"}) {
    if (auto r = Query(sql); !r.ok()) return r.status();
  }
  if (auto r = Query(core::StrCat("PRAGMA user_version = ", kSchemaVersion)); !r.ok()) return r.status();
  return absl::OkStatus();
}

SqliteJobStore::~SqliteJobStore() { sqlite3_close(db_); }

absl::StatusOr<std::vector<SqliteJobStore::Row>> SqliteJobStore::Query(const std::string& sql,
                                                                       const std::vector<std::string>& params) {
  sqlite3_stmt* st = nullptr;
  if (sqlite3_prepare_v2(db_, sql.c_str(), -1, &st, nullptr) != SQLITE_OK) {
    return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  }
  for (size_t i = 0; i < params.size(); ++i) {
    sqlite3_bind_text(st, static_cast<int>(i + 1), params[i].c_str(), static_cast<int>(params[i].size()),
                      SQLITE_TRANSIENT);
  }
  std::vector<Row> out;
  int rc = SQLITE_ROW;
  while ((rc = sqlite3_step(st)) == SQLITE_ROW) {
    Row& row = out.emplace_back(static_cast<size_t>(sqlite3_column_count(st)));
    for (int i = 0; i < sqlite3_column_count(st); ++i) {
      const auto* text = sqlite3_column_text(st, i);
      if (text != nullptr) row[static_cast<size_t>(i)] = reinterpret_cast<const char*>(text);
    }
  }
  sqlite3_finalize(st);
  if (rc != SQLITE_DONE) {
    const int code = sqlite3_extended_errcode(db_);
    std::string msg = core::StrCat("job database: ", sqlite3_errmsg(db_));
    if (code == SQLITE_CONSTRAINT_PRIMARYKEY) return absl::AlreadyExistsError(msg);
    if (code == SQLITE_FULL) return absl::ResourceExhaustedError(core::StrCat(msg, " (the server's disk is full)"));
    return absl::UnavailableError(msg);
  }
  return out;
}

absl::StatusOr<std::vector<JobRecord>> SqliteJobStore::QueryJobs(const std::string& where,
                                                                 const std::vector<std::string>& params) {
  auto found = Query(core::StrCat("SELECT ", rows::ColumnList(), " FROM jobs ", where), params);
  if (!found.ok()) return found.status();
  std::vector<JobRecord> out;
  out.reserve(found->size());
  for (const Row& row : *found) out.push_back(rows::FromColumns(row, tables_));
  return out;
}

absl::Status SqliteJobStore::Insert(const JobRecord& record) {
  std::lock_guard lock(mutex_);
  std::vector<std::string> values = rows::JobColumns(rows::WithFormat(record, tables_.format));
  values.push_back(std::to_string(++seq_));
  std::string placeholders;
  for (int i = 1; i <= rows::kColumnCount; ++i) core::StrAppend(&placeholders, i > 1 ? ", ?" : "?", i);
  auto r = Query(core::StrCat("INSERT INTO jobs (", rows::ColumnList(), ") VALUES (", placeholders, ")"), values);
  return r.status();
}

absl::StatusOr<int64_t> SqliteJobStore::Replace(const JobRecord& record, const std::string& held_by) {
  std::vector<std::string> values = rows::HeldColumns(record);
  const int64_t seq = ++seq_;
  values.push_back(std::to_string(seq));
  values.push_back(held_by);
  const size_t n = values.size();
  auto r =
      Query(core::StrCat("UPDATE jobs SET ", rows::HeldAssignments('?'), ", seq = ?", n - 1,
                         rows::WithStates(" WHERE id = ?1 AND state = {running} AND runner = ?"), n, " RETURNING id"),
            values);
  if (!r.ok()) return r.status();
  if (r->empty()) return absl::AbortedError(core::StrCat("job ", record.id, " is not held by ", held_by));
  return seq;
}

absl::StatusOr<std::optional<JobRecord>> SqliteJobStore::Claim(const std::string& runner,
                                                               std::chrono::milliseconds lease,
                                                               const ClaimScope& scope) {
  std::lock_guard lock(mutex_);
  const int64_t now = NowMs();
  auto claimed = Query(
      core::StrCat(rows::WithStates("UPDATE jobs SET state = {running}, stage = 'starting', progress = 0, "
                                    "attempts = attempts + 1, cancel_requested = 0, runner = ?1, "
                                    "lease_expires_ms = ?2, updated_ms = ?3, seq = ?4 WHERE id = (SELECT id FROM jobs "
                                    "WHERE state = {queued} AND ((parent = '' AND ?6 = '' AND spec_format <= ?5) OR "
                                    "(parent <> '' AND spec_format = CAST(?7 AS INTEGER) AND (?6 = '' OR parent = ?6) "
                                    "AND parent IN (SELECT p.id FROM jobs p WHERE p.state = {running}))) ORDER BY "
                                    "parent = '', created_ms, child_index, id LIMIT 1) RETURNING "),
                   rows::ColumnList()),
      {runner, std::to_string(now + lease.count()), std::to_string(now), std::to_string(seq_ + 1),
       std::to_string(tables_.format), scope.parent, std::to_string(scope.child_format)});
  if (!claimed.ok()) return claimed.status();
  if (claimed->empty()) return std::optional<JobRecord>();
  ++seq_;
  return std::optional<JobRecord>(rows::FromColumns(claimed->front(), tables_));
}

absl::StatusOr<int64_t> SqliteJobStore::WriteHeld(const JobRecord& record) {
  std::lock_guard lock(mutex_);
  return Replace(record, record.runner);
}

absl::StatusOr<std::vector<std::pair<std::string, bool>>> SqliteJobStore::Renew(const std::string& runner,
                                                                                const std::vector<std::string>& ids,
                                                                                std::chrono::milliseconds lease) {
  if (ids.empty()) return std::vector<std::pair<std::string, bool>>();
  std::lock_guard lock(mutex_);
  std::vector<std::string> params = {runner, std::to_string(NowMs() + lease.count())};
  std::string list;
  for (const std::string& id : ids) {
    params.push_back(id);
    core::StrAppend(&list, list.empty() ? "?" : ", ?", params.size());
  }
  auto held = Query(core::StrCat(rows::WithStates("UPDATE jobs SET lease_expires_ms = ?2 WHERE state = {running} AND "
                                                  "runner = ?1 AND id IN ("),
                                 list, ") RETURNING id, cancel_requested"),
                    params);
  if (!held.ok()) return held.status();
  std::vector<std::pair<std::string, bool>> out;
  for (const Row& row : *held) out.emplace_back(row[0], rows::ToInt(row[1]) != 0);
  return out;
}

absl::StatusOr<std::vector<JobRecord>> SqliteJobStore::RecoverLapsed(bool every_running,
                                                                     const std::function<void(JobRecord&)>& recover) {
  std::lock_guard lock(mutex_);
  auto lapsed =
      QueryJobs(rows::WithStates(every_running ? "WHERE state = {running}"
                                               : "WHERE state = {running} AND lease_expires_ms <= ?1"),
                every_running ? std::vector<std::string>{} : std::vector<std::string>{std::to_string(NowMs())});
  if (!lapsed.ok()) return lapsed.status();
  std::vector<JobRecord> out;
  for (JobRecord& r : *lapsed) {
    const std::string runner = r.runner;
    recover(r);
    auto seq = Replace(r, runner);
    if (seq.status().code() == absl::StatusCode::kAborted) continue;
    if (!seq.ok()) return seq.status();
    r.seq = *seq;
    out.push_back(std::move(r));
  }
  return out;
}

absl::StatusOr<JobRecord> SqliteJobStore::Cancel(const std::string& id, const std::string& reason) {
  std::lock_guard lock(mutex_);
  const std::string now = std::to_string(NowMs());
  bool changed_here = false;
  // A queued job wrote nothing: its stored bytes settle to its upload (the reserve goes).
  for (const char* sql :
       {"UPDATE jobs SET state = {cancelled}, error = ?2, updated_ms = ?3, seq = ?4, stored_bytes = input_bytes "
        "WHERE id = ?1 AND state = {queued} RETURNING id",
        "UPDATE jobs SET cancel_requested = 1, updated_ms = ?3, seq = ?4 WHERE id = ?1 AND "
        "state = {running} RETURNING id"}) {
    auto changed = Query(rows::WithStates(sql), {id, reason, now, std::to_string(seq_ + 1)});
    if (!changed.ok()) return changed.status();
    if (!changed->empty()) {
      ++seq_;
      changed_here = true;
      break;
    }
  }
  auto found = QueryJobs("WHERE id = ?1", {id});
  if (!found.ok()) return found.status();
  if (found->empty()) return NoSuchJob(id);
  JobRecord& r = found->front();
  if (!changed_here) return AlreadyFinished(r);
  return std::move(r);
}

absl::Status SqliteJobStore::Remove(const std::string& id) {
  std::lock_guard lock(mutex_);
  auto removed = Query(rows::WithStates("DELETE FROM jobs WHERE id = ?1 AND state IN {finished} RETURNING id"), {id});
  if (!removed.ok()) return removed.status();
  if (removed->empty()) {
    auto found = QueryJobs("WHERE id = ?1", {id});
    if (!found.ok()) return found.status();
    return found->empty() ? NoSuchJob(id) : NotFinished(found->front());
  }
  auto children = Query("DELETE FROM jobs WHERE parent = ?1 RETURNING id", {id});
  if (!children.ok()) return children.status();
  children->push_back({id});
  for (const Row& gone : *children) {
    auto r = Query("INSERT OR REPLACE INTO job_removals (id, seq) VALUES (?1, ?2)", {gone[0], std::to_string(++seq_)});
    if (!r.ok()) return r.status();
  }
  return absl::OkStatus();
}

absl::StatusOr<JobRecord> SqliteJobStore::Get(const std::string& id) {
  std::lock_guard lock(mutex_);
  auto found = QueryJobs("WHERE id = ?1", {id});
  if (!found.ok()) return found.status();
  if (found->empty()) return NoSuchJob(id);
  return std::move(found->front());
}

absl::StatusOr<JobChanges> SqliteJobStore::ChangesSince(int64_t seq) {
  std::lock_guard lock(mutex_);
  JobChanges out;
  out.seq = seq_;
  const std::vector<std::string> params{std::to_string(seq)};
  auto changed = QueryJobs("WHERE seq > ?1 ORDER BY seq", params);
  if (!changed.ok()) return changed.status();
  out.changed = *std::move(changed);
  auto removed = Query("SELECT id FROM job_removals WHERE seq > ?1 ORDER BY seq", params);
  if (!removed.ok()) return removed.status();
  for (Row& row : *removed) out.removed.push_back(std::move(row[0]));
  return out;
}

void SqliteJobStore::WaitForOthers(std::chrono::milliseconds timeout) {
  // Nobody else writes to this database.
  std::this_thread::sleep_for(timeout);
}

absl::StatusOr<std::string> SqliteJobStore::Agree(const std::string& key, const std::string& value) {
  std::lock_guard lock(mutex_);
  if (auto r = Query("INSERT OR IGNORE INTO settings (key, value) VALUES (?1, ?2)", {key, value}); !r.ok()) {
    return r.status();
  }
  auto kept = Query("SELECT value FROM settings WHERE key = ?1", {key});
  if (!kept.ok()) return kept.status();
  if (kept->empty()) return absl::UnavailableError(core::StrCat("the setting '", key, "' was not kept"));
  return kept->front().front();
}

}  // namespace lsqsurf::jobs
