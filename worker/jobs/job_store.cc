#include "worker/jobs/job_store.h"

#include <sqlite3.h>

#include <charconv>
#include <sstream>

#include "worker/core/strings.h"

namespace lsqsurf::jobs {
namespace {

// Flat "name=value;name=value" text for parameter and statistics lists: readable in the
// sqlite3 shell and free of any JSON dependency. Names never contain '=' or ';'.
template <class Pairs>
std::string EncodePairs(const Pairs& pairs) {
  std::string out;
  for (const auto& [name, value] : pairs) {
    char buf[32];
    const auto r = std::to_chars(buf, buf + sizeof(buf), value);
    core::StrAppend(&out, name, "=", std::string_view(buf, static_cast<size_t>(r.ptr - buf)), ";");
  }
  return out;
}

std::vector<std::pair<std::string, double>> DecodePairs(std::string_view text) {
  std::vector<std::pair<std::string, double>> out;
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

// The preview as numeric pairs (the colour attribute's name goes in its own column); an empty
// text means no preview.
std::string EncodePreview(const PreviewSpec& p) {
  if (!p.enabled) return "";
  const render::RenderParams& r = p.render;
  const std::vector<std::pair<std::string, double>> pairs = {
      {"width", r.width}, {"height", r.height}, {"up", static_cast<double>(r.camera.up)},
      {"azimuth", r.camera.azimuth_deg}, {"elevation", r.camera.elevation_deg},
      {"distance", r.camera.distance}, {"fov", r.camera.fov_deg}, {"color_min", r.color_min},
      {"color_max", r.color_max}, {"flat", r.shading == render::Shading::kFlat ? 1.0 : 0.0},
      {"wireframe", r.wireframe ? 1.0 : 0.0}, {"transparent", r.transparent ? 1.0 : 0.0},
      {"samples", r.samples}, {"turntable", p.turntable_deg_per_frame}};
  return EncodePairs(pairs);
}

PreviewSpec DecodePreview(std::string_view text, std::string colour) {
  PreviewSpec p;
  if (text.empty()) return p;
  p.enabled = true;
  render::RenderParams& r = p.render;
  r.color_attribute = std::move(colour);
  for (const auto& [name, v] : DecodePairs(text)) {
    if (name == "width") r.width = static_cast<int>(v);
    if (name == "height") r.height = static_cast<int>(v);
    if (name == "up") r.camera.up = static_cast<render::UpAxis>(std::clamp(static_cast<int>(v), 0, 2));
    if (name == "azimuth") r.camera.azimuth_deg = v;
    if (name == "elevation") r.camera.elevation_deg = v;
    if (name == "distance") r.camera.distance = v;
    if (name == "fov") r.camera.fov_deg = v;
    if (name == "color_min") r.color_min = v;
    if (name == "color_max") r.color_max = v;
    if (name == "flat") r.shading = v != 0 ? render::Shading::kFlat : render::Shading::kSmooth;
    if (name == "wireframe") r.wireframe = v != 0;
    if (name == "transparent") r.transparent = v != 0;
    if (name == "samples") r.samples = static_cast<int>(v);
    if (name == "turntable") p.turntable_deg_per_frame = v;
  }
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

absl::StatusOr<std::unique_ptr<JobStore>> JobStore::Open(const std::string& path) {
  sqlite3* db = nullptr;
  if (sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX,
                      nullptr) != SQLITE_OK) {
    std::string msg = db ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::UnavailableError(core::StrCat("cannot open job database ", path, ": ", msg));
  }
  std::unique_ptr<JobStore> store(new JobStore(db));
  for (const char* sql : {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=FULL",
                          "CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, method TEXT, "
                          "parameters TEXT, mesh_bits INTEGER, state INTEGER, stage TEXT, "
                          "attempts INTEGER, error TEXT, created_ms INTEGER, updated_ms INTEGER, "
                          "input_points INTEGER, input_bytes INTEGER, statistics TEXT, results TEXT, "
                          "preview TEXT, preview_color TEXT)"}) {
    if (absl::Status s = store->Exec(sql); !s.ok()) return s;
  }
  // Databases written before previews existed lack their columns.
  for (const char* column : {"preview", "preview_color"}) {
    if (!store->HasColumn(column)) {
      if (absl::Status s = store->Exec(core::StrCat("ALTER TABLE jobs ADD COLUMN ", column, " TEXT").c_str()); !s.ok()) {
        return s;
      }
    }
  }
  return store;
}

JobStore::~JobStore() { sqlite3_close(db_); }

absl::Status JobStore::Exec(const char* sql) {
  char* err = nullptr;
  if (sqlite3_exec(db_, sql, nullptr, nullptr, &err) != SQLITE_OK) {
    std::string msg = err ? err : "unknown error";
    sqlite3_free(err);
    return absl::UnavailableError(core::StrCat("job database: ", msg));
  }
  return absl::OkStatus();
}

bool JobStore::HasColumn(const char* name) {
  sqlite3_stmt* st = nullptr;
  if (sqlite3_prepare_v2(db_, "SELECT name FROM pragma_table_info('jobs')", -1, &st, nullptr) != SQLITE_OK) return false;
  bool found = false;
  while (!found && sqlite3_step(st) == SQLITE_ROW) found = Column(st, 0) == name;
  sqlite3_finalize(st);
  return found;
}

absl::Status JobStore::Put(const JobRecord& r) {
  std::lock_guard lock(mutex_);
  sqlite3_stmt* st = nullptr;
  const char* sql =
      "INSERT OR REPLACE INTO jobs (id, method, parameters, mesh_bits, state, stage, attempts, "
      "error, created_ms, updated_ms, input_points, input_bytes, statistics, results, preview, preview_color) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16)";
  if (sqlite3_prepare_v2(db_, sql, -1, &st, nullptr) != SQLITE_OK) {
    return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  }
  std::string results;
  for (const auto& name : r.results) results += name + ";";
  const std::string params = EncodePairs(r.spec.parameters), stats = EncodePairs(r.statistics);
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
  sqlite3_bind_text(st, 16, r.spec.preview.render.color_attribute.c_str(), -1, SQLITE_TRANSIENT);
  const int rc = sqlite3_step(st);
  sqlite3_finalize(st);
  if (rc != SQLITE_DONE) return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  return absl::OkStatus();
}

absl::Status JobStore::Remove(const std::string& id) {
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

absl::StatusOr<std::vector<JobRecord>> JobStore::LoadAll() {
  std::lock_guard lock(mutex_);
  sqlite3_stmt* st = nullptr;
  const char* sql =
      "SELECT id, method, parameters, mesh_bits, state, stage, attempts, error, created_ms, "
      "updated_ms, input_points, input_bytes, statistics, results, preview, preview_color FROM jobs "
      "ORDER BY created_ms, id";
  if (sqlite3_prepare_v2(db_, sql, -1, &st, nullptr) != SQLITE_OK) {
    return absl::UnavailableError(core::StrCat("job database: ", sqlite3_errmsg(db_)));
  }
  std::vector<JobRecord> out;
  while (sqlite3_step(st) == SQLITE_ROW) {
    JobRecord r;
    r.id = Column(st, 0);
    r.spec.method = Column(st, 1);
    for (auto& [k, v] : DecodePairs(Column(st, 2))) r.spec.parameters[k] = v;
    r.spec.mesh_position_bits = sqlite3_column_int(st, 3);
    r.state = static_cast<JobState>(std::clamp(sqlite3_column_int(st, 4), 0, 4));
    r.stage = Column(st, 5);
    r.attempts = sqlite3_column_int(st, 6);
    r.error = Column(st, 7);
    r.created_ms = sqlite3_column_int64(st, 8);
    r.updated_ms = sqlite3_column_int64(st, 9);
    r.input_points = sqlite3_column_int64(st, 10);
    r.input_bytes = sqlite3_column_int64(st, 11);
    r.statistics = DecodePairs(Column(st, 12));
    std::stringstream ss(Column(st, 13));
    for (std::string name; std::getline(ss, name, ';');) {
      if (!name.empty()) r.results.push_back(name);
    }
    r.spec.preview = DecodePreview(Column(st, 14), Column(st, 15));
    if (IsTerminal(r.state)) r.progress = r.state == JobState::kSucceeded ? 1.0 : 0.0;
    out.push_back(std::move(r));
  }
  sqlite3_finalize(st);
  return out;
}

}  // namespace lsqsurf::jobs
