#include "worker/jobs/store/job_rows.h"

#include <algorithm>
#include <charconv>
#include <sstream>

#include "absl/strings/str_replace.h"
#include "worker/core/strings.h"

namespace lsqsurf::jobs::rows {
namespace {

// Statistics as flat "name=value;" text: readable in a database shell. Names never contain
// '=' or ';'.
std::string EncodeStatistics(const Statistics& pairs) {
  std::string out;
  for (const auto& [name, value] : pairs) core::StrAppend(&out, name, "=", Number(value), ";");
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
  return core::StrCat(p.view.Encode(), "turntable=", Number(p.turntable_deg_per_frame), ";");
}

PreviewSpec DecodePreview(std::string_view text, std::string colour, const SpecTables& tables) {
  PreviewSpec p;
  if (text.empty()) return p;
  p.enabled = true;
  p.view = tables.view();
  // Rows written before the view options had a table used shorter names.
  static const std::pair<const char*, const char*> kRenamed[] = {{"up", "up_axis"},
                                                                 {"azimuth", "azimuth_deg"},
                                                                 {"elevation", "elevation_deg"},
                                                                 {"fov", "fov_deg"},
                                                                 {"flat", "flat_shading"}};
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

double ToDouble(const std::string& text) {
  double v = 0;
  std::from_chars(text.data(), text.data() + text.size(), v);
  return v;
}

}  // namespace

std::string WithStates(std::string_view sql) {
  const auto text = [](JobState state) { return std::to_string(static_cast<int>(state)); };
  const std::vector<std::pair<std::string, std::string>> names = {
      {"{queued}", text(JobState::kQueued)},
      {"{running}", text(JobState::kRunning)},
      {"{succeeded}", text(JobState::kSucceeded)},
      {"{failed}", text(JobState::kFailed)},
      {"{cancelled}", text(JobState::kCancelled)},
      {"{finished}", core::StrCat("(", text(JobState::kSucceeded), ", ", text(JobState::kFailed), ", ",
                                  text(JobState::kCancelled), ")")}};
  return absl::StrReplaceAll(absl::string_view(sql.data(), sql.size()), names);
}

std::string Number(double value) {
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof(buf), value);
  return std::string(buf, static_cast<size_t>(r.ptr - buf));
}

int64_t ToInt(const std::string& text) {
  int64_t v = 0;
  std::from_chars(text.data(), text.data() + text.size(), v);
  return v;
}

const std::string& ColumnList() {
  static const auto* list = new std::string([] {
    std::string out;
    for (const char* name : kColumnNames) core::StrAppend(&out, out.empty() ? "" : ", ", name);
    return out;
  }());
  return *list;
}

namespace {
// The spec format stays the one the job was stored with, a child job its parent's.
bool IsHeldColumn(std::string_view name) {
  return name != "id" && name != "seq" && name != "cancel_requested" && name != "spec_format" && name != "parent" &&
         name != "child_index";
}
}  // namespace

std::string HeldAssignments(char placeholder) {
  std::string out;
  int param = 2;
  for (const char* name : kColumnNames) {
    if (!IsHeldColumn(name)) continue;
    core::StrAppend(&out, param > 2 ? ", " : "", name, " = ", std::string(1, placeholder), param);
    ++param;
  }
  return out;
}

std::vector<std::string> HeldColumns(const JobRecord& record) {
  std::vector<std::string> all = JobColumns(record), out;
  for (int i = 0; i + 1 < kColumnCount; ++i) {
    if (i == 0 || IsHeldColumn(kColumnNames[i])) out.push_back(std::move(all[static_cast<size_t>(i)]));
  }
  return out;
}

std::vector<std::string> JobColumns(const JobRecord& r) {
  std::string results;
  for (const auto& name : r.results) core::StrAppend(&results, name, ";");
  const std::string colour = r.spec.preview.enabled ? r.spec.preview.view.GetText("color").value_or("") : "";
  return {r.id,
          r.spec.method,
          r.spec.params.Encode(),
          std::to_string(r.spec.mesh_position_bits),
          std::to_string(static_cast<int>(r.state)),
          r.stage,
          std::to_string(r.attempts),
          r.error,
          std::to_string(r.created_ms),
          std::to_string(r.updated_ms),
          std::to_string(r.input_points),
          std::to_string(r.input_bytes),
          EncodeStatistics(r.statistics),
          results,
          EncodePreview(r.spec.preview),
          colour,
          std::to_string(r.interruptions),
          Number(r.progress),
          r.runner,
          r.cancel_requested ? "1" : "0",
          r.owner,
          std::to_string(r.stored_bytes),
          std::to_string(r.quota_bytes),
          std::to_string(r.spec_format),
          r.parent,
          std::to_string(r.child_index)};
}

JobRecord WithFormat(JobRecord record, int format) {
  if (!IsChildJob(record)) record.spec_format = format;
  return record;
}

JobRecord FromColumns(const std::vector<std::string>& c, const SpecTables& tables) {
  JobRecord r;
  r.id = c[0];
  r.spec.method = c[1];
  std::string unusable;  // Why the stored spec cannot run any more.
  r.parent = c[24];
  if (IsChildJob(r)) {
    // A child job's spec is its parent's business (a tile of a build): nothing to decode.
  } else if (auto params = tables.params(r.spec.method); params.ok()) {
    r.spec.params = *std::move(params);
    if (absl::Status s = r.spec.params.Decode(c[2]); !s.ok()) unusable = std::string(s.message());
  } else {
    unusable = core::StrCat("this server has no method '", r.spec.method, "' any more");
  }
  r.spec.mesh_position_bits = static_cast<int>(ToInt(c[3]));
  r.state = static_cast<JobState>(std::clamp<int64_t>(ToInt(c[4]), 0, static_cast<int64_t>(kLastJobState)));
  r.stage = c[5];
  r.attempts = static_cast<int>(ToInt(c[6]));
  r.error = c[7];
  r.created_ms = ToInt(c[8]);
  r.updated_ms = ToInt(c[9]);
  r.input_points = ToInt(c[10]);
  r.input_bytes = ToInt(c[11]);
  r.statistics = DecodeStatistics(c[12]);
  std::stringstream ss(c[13]);
  for (std::string name; std::getline(ss, name, ';');) {
    if (!name.empty()) r.results.push_back(name);
  }
  r.spec.preview = DecodePreview(c[14], c[15], tables);
  r.interruptions = static_cast<int>(ToInt(c[16]));
  r.progress = ToDouble(c[17]);
  r.runner = c[18];
  r.cancel_requested = ToInt(c[19]) != 0;
  r.owner = c[20];
  r.stored_bytes = ToInt(c[21]);
  r.quota_bytes = ToInt(c[22]);
  r.spec_format = static_cast<int>(ToInt(c[23]));
  r.child_index = ToInt(c[25]);
  r.seq = ToInt(c[26]);
  // A stored spec that no longer decodes cannot run: it fails with the reason. One of a newer
  // format is left as it is: a newer server runs it.
  if (!unusable.empty() && !IsTerminal(r.state) && r.spec_format <= tables.format) {
    r.state = JobState::kFailed;
    r.error = std::move(unusable);
  }
  if (IsTerminal(r.state)) r.progress = r.state == JobState::kSucceeded ? 1.0 : 0.0;
  return r;
}

}  // namespace lsqsurf::jobs::rows
