#include "worker/jobs/job_store.h"

#include <sqlite3.h>

#include <charconv>
#include <sstream>

#include "worker/core/strings.h"
#include "worker/jobs/method_registry.h"

namespace lsqsurf::jobs {
namespace {

// Statistics as flat "name=value;" text: readable in the sqlite3 shell. Names never contain
// '=' or ';'.
std::string EncodeStatistics(const Statistics& pairs) {
  std::string out;
  for (const auto& [name, value] : pairs) {
    char buf[32];
    const auto r = std::to_chars(buf, buf + sizeof(buf), value);
    core::StrAppend(&out, name, "=", std::string_view(buf, static_cast<size_t>(r.ptr - buf)), ";");
  }
  return out;
}

Statistics DecodeStatistics(std::string_view text) {
  Statistics out;
  while (!text.empty()) {
    const size_t end = text.find(';');
    const std::string_view item = text.substr(0, end);
    const size_t eq = item.find('=');
    if (eq != std::string_view::npos) {
      double v = 0;
      std::from_chars(item.data() + eq + 1, item.data() + item.size(), v);
      out.emplace_back(std::string(item.substr(0, eq)), v);
    }
    if (end == std::string_view::npos) break;
    text.remove_prefix(end + 1);
  }
  return out;
}

// The preview column: the view options in their table's text form plus the turntable step;
// empty means no preview. The colour attribute is kept in its own column, as before.
std::string EncodePreview(const PreviewSpec& p) {
  if (!p.enabled) return "";
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof(buf), p.turntable_deg_per_frame);
  return core::StrCat(p.view.Encode(), "turntable=", std::string_view(buf, static_cast<size_t>(r.ptr - buf)), ";");
}

PreviewSpec DecodePreview(std::string_view text, std::string colour) {
  PreviewSpec p;
  if (text.empty()) return p;
  p.enabled = true;
  p.view = DefaultView();
  // Rows written before the view options had a table used shorter names.
  static const std::pair<const char*, const char*> kRenamed[] = {{"up", "up_axis"},
                                                                 {"azimuth", "azimuth_deg"},
                                                                 {"elevation", "elevation_deg"},
                                                                 {"fov", "fov_deg"},
                                                                 {"flat", "flat_shading"}};
  std::string current;
  for (const auto& [name, value] : DecodeStatistics(text)) {
    if (name == "turntable") {
      p.turntable_deg_per_frame = value;
      continue;
    }
    std::string field = name;
    for (const auto& [old_name, new_name] : kRenamed) {
      if (name == old_name) field = new_name;
    }
    if (field == "color") continue;
    (void)p.view.Set(field, value);  // A value that no longer fits keeps the default.
  }
  if (!colour.empty()) (void)p.view.SetText("color", std::move(colour));
  return p;
}

std::string Column(sqlite3_stmt* st, int i) {
  const auto* text = sqlite3_column_text(st, i);
  return text ? reinterpret_cast<const char*>(text) : "";
}

}  // namespace

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

absl::StatusOr<std::unique_ptr<SqliteJobStore>> SqliteJobStore::Open(const std::string& path) {
  sqlite3* db = nullptr;
  if (sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX, nullptr) !=
      SQLITE_OK) {
    std::string msg = db ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::UnavailableError(core::StrCat("cannot open job database ", path, ": ", msg));
  }
  std::unique_ptr<SqliteJobStore> store(new SqliteJobStore(db));
  for (const char* sql : {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=FULL",
                          "CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, method TEXT, "
                          "parameters TEXT, mesh_bits INTEGER, state INTEGER, stage TEXT, "
                          "attempts INTEGER, error TEXT, created_ms INTEGER, updated_ms INTEGER, "
                          "input_points INTEGER, input_bytes INTEGER, statistics TEXT, results TEXT, "
                          "preview TEXT, preview_color TEXT, interruptions INTEGER)"}) {
    if (absl::Status s = store->Exec(sql); !s.ok()) return s;
  }
  // Databases written by earlier versions lack the later columns.
  for (const char* column : {"preview TEXT", "preview_color TEXT", "interruptions INTEGER"}) {
    const std::string name(column, std::string_view(column).find(' '));
    if (!store->HasColumn(name.c_str())) {
      if (absl::Status s = store->Exec(core::StrCat("ALTER TABLE jobs ADD COLUMN ", column).c_str()); !s.ok()) {
        return s;
      }
    }
  }
  return store;
}

SqliteJobStore::~SqliteJobStore() { sqlite3_close(db_); }

absl::Status SqliteJobStore::Exec(const char* sql) {
  char* err = nullptr;
  if (sqlite3_exec(db_, sql, nullptr, nullptr, &err) != SQLITE_OK) {
    std::string msg = err ? err : "unknown error";
    sqlite3_free(err);
    return absl::UnavailableError(core::StrCat("job database: ", msg));
  }
  return absl::OkStatus();
}

bool SqliteJobStore::HasColumn(const char* name) {
  sqlite3_stmt* st = nullptr;
  if (sqlite3_prepare_v2(db_, "SELECT name FROM pragma_table_info('jobs')", -1, &st, nullptr) != SQLITE_OK)
    return false;
  bool found = false;
  while (!found && sqlite3_step(st) == SQLITE_ROW) found = Column(st, 0) == name;
  sqlite3_finalize(st);
  return found;
}

absl::Status SqliteJobStore::Put(const JobRecord& r) {
  std::lock_guard lock(mutex_);
  sqlite3_stmt* st = nullptr;
  const char* sql =
      "INSERT OR REPLACE INTO jobs (id, method, parameters, mesh_bits, state, stage, attempts, "
      "error, created_ms, updated_ms, input_points, input_bytes, statistics, results, preview, preview_color, "
      "interruptions) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17)";
  if (sqlite3_prepare_v2(db_, sql, -1, &st, nullptr) != SQLITE_OK) {
    return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  }
  std::string results;
  for (const auto& name : r.results) results += name + ";";
  const std::string params = r.spec.params.Encode(), stats = EncodeStatistics(r.statistics);
  sqlite3_bind_text(st, 1, r.id.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_text(st, 2, r.spec.method.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_text(st, 3, params.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int(st, 4, r.spec.mesh_position_bits);
  sqlite3_bind_int(st, 5, static_cast<int>(r.state));
  sqlite3_bind_text(st, 6, r.stage.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int(st, 7, r.attempts);
  sqlite3_bind_text(st, 8, r.error.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int64(st, 9, r.created_ms);
  sqlite3_bind_int64(st, 10, r.updated_ms);
  sqlite3_bind_int64(st, 11, r.input_points);
  sqlite3_bind_int64(st, 12, r.input_bytes);
  sqlite3_bind_text(st, 13, stats.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_text(st, 14, results.c_str(), -1, SQLITE_TRANSIENT);
  const std::string preview = EncodePreview(r.spec.preview);
  sqlite3_bind_text(st, 15, preview.c_str(), -1, SQLITE_TRANSIENT);
  const std::string colour = r.spec.preview.enabled ? r.spec.preview.view.GetText("color").value_or("") : "";
  sqlite3_bind_text(st, 16, colour.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int(st, 17, r.interruptions);
  const int rc = sqlite3_step(st);
  sqlite3_finalize(st);
  if (rc != SQLITE_DONE) return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  return absl::OkStatus();
}

absl::Status SqliteJobStore::Remove(const std::string& id) {
  std::lock_guard lock(mutex_);
  sqlite3_stmt* st = nullptr;
  if (sqlite3_prepare_v2(db_, "DELETE FROM jobs WHERE id = ?1", -1, &st, nullptr) != SQLITE_OK) {
    return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  }
  sqlite3_bind_text(st, 1, id.c_str(), -1, SQLITE_TRANSIENT);
  const int rc = sqlite3_step(st);
  sqlite3_finalize(st);
  if (rc != SQLITE_DONE) return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  return absl::OkStatus();
}

absl::StatusOr<std::vector<JobRecord>> SqliteJobStore::LoadAll() {
  std::lock_guard lock(mutex_);
  sqlite3_stmt* st = nullptr;
  const char* sql =
      "SELECT id, method, parameters, mesh_bits, state, stage, attempts, error, created_ms, "
      "updated_ms, input_points, input_bytes, statistics, results, preview, preview_color, interruptions FROM jobs "
      "ORDER BY created_ms, id";
  if (sqlite3_prepare_v2(db_, sql, -1, &st, nullptr) != SQLITE_OK) {
    return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  }
  std::vector<JobRecord> out;
  while (sqlite3_step(st) == SQLITE_ROW) {
    JobRecord r;
    r.id = Column(st, 0);
    r.spec.method = Column(st, 1);
    std::string unusable;  // Why the stored spec cannot run any more.
    if (auto params = DefaultParams(r.spec.method); params.ok()) {
      r.spec.params = *std::move(params);
      if (absl::Status s = r.spec.params.Decode(Column(st, 2)); !s.ok()) unusable = std::string(s.message());
    } else {
      unusable = core::StrCat("this server has no method '", r.spec.method, "' any more");
    }
    r.spec.mesh_position_bits = sqlite3_column_int(st, 3);
    r.state = static_cast<JobState>(std::clamp(sqlite3_column_int(st, 4), 0, 4));
    r.stage = Column(st, 5);
    r.attempts = sqlite3_column_int(st, 6);
    r.error = Column(st, 7);
    r.created_ms = sqlite3_column_int64(st, 8);
    r.updated_ms = sqlite3_column_int64(st, 9);
    r.input_points = sqlite3_column_int64(st, 10);
    r.input_bytes = sqlite3_column_int64(st, 11);
    r.statistics = DecodeStatistics(Column(st, 12));
    std::stringstream ss(Column(st, 13));
    for (std::string name; std::getline(ss, name, ';');) {
      if (!name.empty()) r.results.push_back(name);
    }
    r.spec.preview = DecodePreview(Column(st, 14), Column(st, 15));
    r.interruptions = sqlite3_column_int(st, 16);
    // A stored spec that no longer decodes cannot run: it fails with the reason.
    if (!unusable.empty() && !IsTerminal(r.state)) {
      r.state = JobState::kFailed;
      r.error = std::move(unusable);
    }
    if (IsTerminal(r.state)) r.progress = r.state == JobState::kSucceeded ? 1.0 : 0.0;
    out.push_back(std::move(r));
  }
  sqlite3_finalize(st);
  return out;
}

}  // namespace lsqsurf::jobs
