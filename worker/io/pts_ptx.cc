#include "worker/io/pts_ptx.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/text_scan.h"

namespace lsqsurf::io {
namespace {

using internal::LineReader;
using internal::NextToken;
using internal::ParseNumber;

constexpr int kMaxValues = 7;  // x y z intensity r g b.

absl::Status LineError(std::string_view name, size_t line, std::string_view what) {
  return absl::InvalidArgumentError(core::StrCat(name, ":", line, ": ", what));
}

// The numbers of a line, at most kMaxValues; -1 when there are more, -2 when one is no number.
int SplitNumbers(std::string_view line, double (&v)[kMaxValues + 1]) {
  int n = 0;
  for (std::string_view tok = NextToken(line); !tok.empty(); tok = NextToken(line)) {
    if (n == kMaxValues) return -1;
    if (!ParseNumber(tok, v[n])) return -2;
    ++n;
  }
  return n;
}

// The attribute columns of a point line with `values` numbers: intensity and/or colour.
struct Columns {
  bool intensity = false, colour = false;
  int first_colour = 3;
};

void AddColumns(const Columns& c, core::PointCloud& cloud) {
  if (!cloud.attributes.empty()) return;
  if (c.colour) {
    for (const char* n : core::kColourChannels) cloud.attributes.push_back({n, {}});
  }
  if (c.intensity) cloud.attributes.push_back({"intensity", {}});
}

void AppendValues(const Columns& c, const double (&v)[kMaxValues + 1], core::PointCloud& cloud) {
  size_t a = 0;
  if (c.colour) {
    for (int i = 0; i < 3; ++i) cloud.attributes[a++].values.push_back(static_cast<float>(v[c.first_colour + i]));
  }
  if (c.intensity) cloud.attributes[a++].values.push_back(static_cast<float>(v[3]));
}

bool WholeCount(std::string_view line, uint64_t& count) {
  std::string_view rest = line;
  const std::string_view tok = NextToken(rest);
  return !tok.empty() && NextToken(rest).empty() && ParseNumber(tok, count);
}

}  // namespace

struct PtsReader::State {
  LineReader lines;
  std::string name;
  int values = 0;  // Per point line, once one is read.
  Columns columns;
};

PtsReader::PtsReader(std::string_view text, std::string_view name)
    : state_(new State{LineReader(text), std::string(name), 0, {}}) {}
PtsReader::~PtsReader() = default;
size_t PtsReader::offset() const { return state_->lines.offset(); }

absl::Status PtsReader::Read(size_t max_points, core::PointCloud& cloud) {
  State& s = *state_;
  std::string_view line;
  double v[kMaxValues + 1];
  for (size_t read = 0; read < max_points && s.lines.Next(line);) {
    uint64_t count = 0;
    if (WholeCount(line, count)) continue;  // A block's count.
    const int n = SplitNumbers(line, v);
    if (n == 0) continue;
    if (n < 0) {
      return LineError(s.name, s.lines.line_number(),
                       n == -1 ? "more than 7 values (x y z intensity r g b)" : "a value is not a number");
    }
    if (s.values == 0) {
      if (n != 3 && n != 4 && n != 6 && n != 7) {
        return LineError(s.name, s.lines.line_number(),
                         core::StrCat("expected x y z [intensity] [r g b]: 3, 4, 6 or 7 values, found ", n));
      }
      s.values = n;
      s.columns = {.intensity = n == 4 || n == 7, .colour = n >= 6, .first_colour = n == 7 ? 4 : 3};
    }
    if (n != s.values) {
      return LineError(s.name, s.lines.line_number(),
                       core::StrCat("expected ", s.values, " values like the lines before, found ", n));
    }
    AddColumns(s.columns, cloud);
    cloud.positions.emplace_back(static_cast<float>(v[0]), static_cast<float>(v[1]), static_cast<float>(v[2]));
    AppendValues(s.columns, v, cloud);
    ++read;
  }
  if (s.values == 0) return absl::InvalidArgumentError(core::StrCat(s.name, ": no points in PTS file"));
  return absl::OkStatus();
}

absl::StatusOr<core::PointCloud> ParsePts(std::string_view text, std::string_view name) {
  PtsReader reader(text, name);
  core::PointCloud cloud;
  LSQSURF_RETURN_IF_ERROR(reader.Read(std::numeric_limits<size_t>::max(), cloud));
  return cloud;
}

namespace {

struct Scan {
  uint64_t points = 0;  // Columns × rows.
  core::Vec3d station;
  Eigen::Matrix4d transform;  // [p 1]·transform.
};

// Moves `reader` past blank lines to the next line with text; false at the end.
bool NextNonBlank(LineReader& reader, std::string_view& line) {
  while (reader.Next(line)) {
    if (line.find_first_not_of(" \t") != std::string_view::npos) return true;
  }
  return false;
}

}  // namespace

struct PtxReader::State {
  std::string name;
  std::string_view text;
  PtxInfo info;
  std::vector<Scan> scans;
  int values = 0;  // Per point line (3, 4 or 7), once one is read.
  Columns columns;
  std::optional<LineReader> lines;
  size_t reading = 0;    // The scan being read.
  uint64_t in_scan = 0;  // Its points read.

  std::string_view header_line;  // A scan header's first line, as ReadHeaders found it.

  absl::Status ReadHeaders();
  absl::Status ReadHeader(LineReader& reader, Scan& scan) const;
};

// Ten lines: columns, rows, the position, three axes, four matrix rows; `reader` is past the first.
absl::Status PtxReader::State::ReadHeader(LineReader& reader, Scan& scan) const {
  std::string_view line;
  uint64_t grid[2] = {0, 0};
  double v[kMaxValues + 1];
  for (int i = 0; i < 10; ++i) {
    if (i > 0 && !reader.Next(line)) {
      return absl::InvalidArgumentError(core::StrCat(name, ": scan ", scans.size() + 1, "'s header ends at line ",
                                                     reader.line_number(), ", before its ten lines"));
    }
    if (i == 0) line = header_line;
    if (i < 2) {
      if (!WholeCount(line, grid[i]) || grid[i] > (uint64_t{1} << 31)) {
        return LineError(name, reader.line_number(), core::StrCat("expected the scan's ", i == 0 ? "columns" : "rows"));
      }
      continue;
    }
    const int want = i < 6 ? 3 : 4;
    if (SplitNumbers(line, v) != want || !std::all_of(v, v + want, [](double x) { return std::isfinite(x); })) {
      return LineError(name, reader.line_number(),
                       core::StrCat("expected ", want, " numbers (",
                                    i == 2  ? "the scanner's position"
                                    : i < 6 ? "an axis of the scanner"
                                            : "a row of the scan's matrix",
                                    ")"));
    }
    if (i == 2) scan.station = core::Vec3d(v[0], v[1], v[2]);
    if (i >= 6) {
      for (int c = 0; c < 4; ++c) scan.transform(i - 6, c) = v[c];
    }
  }
  scan.points = grid[0] * grid[1];
  return absl::OkStatus();
}

absl::Status PtxReader::State::ReadHeaders() {
  LineReader reader(text);
  while (NextNonBlank(reader, header_line)) {
    Scan scan;
    LSQSURF_RETURN_IF_ERROR(ReadHeader(reader, scan));
    // Its point lines are counted now and read later.
    std::string_view line;
    for (uint64_t p = 0; p < scan.points; ++p) {
      if (!reader.Next(line)) {
        return absl::InvalidArgumentError(core::StrCat(name, ": scan ", scans.size() + 1, " ends after ", p, " of its ",
                                                       scan.points, " points (columns × rows)"));
      }
    }
    info.stations.push_back(scan.station);
    info.points += scan.points;
    scans.push_back(scan);
  }
  if (scans.empty()) return absl::InvalidArgumentError(core::StrCat(name, ": no scans in PTX file"));
  lines.emplace(text);
  return absl::OkStatus();
}

PtxReader::PtxReader(std::unique_ptr<State> state) : state_(std::move(state)) {}
PtxReader::~PtxReader() = default;
const PtxInfo& PtxReader::info() const { return state_->info; }
size_t PtxReader::offset() const { return state_->lines ? state_->lines->offset() : 0; }

absl::StatusOr<std::unique_ptr<PtxReader>> PtxReader::Open(std::string_view text, std::string name) {
  auto state = std::make_unique<State>();
  state->name = std::move(name);
  state->text = text;
  LSQSURF_RETURN_IF_ERROR(state->ReadHeaders());
  return std::unique_ptr<PtxReader>(new PtxReader(std::move(state)));
}

absl::Status PtxReader::Read(size_t max_points, core::PointCloud& cloud) {
  State& s = *state_;
  const bool many = s.scans.size() > 1;
  std::string_view line;
  double v[kMaxValues + 1];
  for (size_t kept = 0; kept < max_points && s.reading < s.scans.size();) {
    const Scan& scan = s.scans[s.reading];
    if (s.in_scan == scan.points) {
      ++s.reading;
      s.in_scan = 0;
      continue;
    }
    if (s.in_scan == 0) {
      // Past blank lines to the header and its ten lines, which Open checked.
      NextNonBlank(*s.lines, line);
      for (int i = 0; i < 9; ++i) s.lines->Next(line);
    }
    s.lines->Next(line);
    ++s.in_scan;
    const int n = SplitNumbers(line, v);
    if (n < 0 || (n != 3 && n != 4 && n != 7)) {
      return LineError(s.name, s.lines->line_number(),
                       n == -2 ? "a value is not a number" : "expected x y z intensity [r g b]: 3, 4 or 7 values");
    }
    if (s.values == 0) {
      s.values = n;
      s.columns = {.intensity = n >= 4, .colour = n == 7, .first_colour = 4};
    }
    if (n != s.values) {
      return LineError(s.name, s.lines->line_number(),
                       core::StrCat("expected ", s.values, " values like the lines before, found ", n));
    }
    if (v[0] == 0 && v[1] == 0 && v[2] == 0) {
      ++s.info.skipped_points;
      continue;
    }
    AddColumns(s.columns, cloud);
    if (many && (cloud.attributes.empty() || cloud.attributes.back().name != "scan")) {
      cloud.attributes.push_back({"scan", {}});
    }
    const Eigen::Vector4d local(v[0], v[1], v[2], 1.0);
    const Eigen::Vector4d world = scan.transform.transpose() * local;
    cloud.positions.emplace_back(static_cast<float>(world[0]), static_cast<float>(world[1]),
                                 static_cast<float>(world[2]));
    AppendValues(s.columns, v, cloud);
    if (many) cloud.attributes.back().values.push_back(static_cast<float>(s.reading));
    ++kept;
  }
  return absl::OkStatus();
}

absl::StatusOr<core::PointCloud> ParsePtx(std::string_view text, std::string_view name, PtxInfo* info) {
  auto reader = PtxReader::Open(text, std::string(name));
  if (!reader.ok()) return reader.status();
  core::PointCloud cloud;
  LSQSURF_RETURN_IF_ERROR((*reader)->Read(std::numeric_limits<size_t>::max(), cloud));
  if (info != nullptr) *info = (*reader)->info();
  return cloud;
}

std::string EncodePtx(const std::vector<PtxScan>& scans) {
  std::string out;
  for (const PtxScan& scan : scans) {
    const core::PointCloud& cloud = *scan.cloud;
    const uint64_t columns = scan.columns == 0 ? 1 : scan.columns;
    const uint64_t rows = scan.columns == 0 ? cloud.size() : scan.rows;
    const core::Vec3d& o = scan.station;
    core::StrAppend(&out, columns, "\n", rows, "\n");
    const auto line = [&out](std::initializer_list<double> values) {
      bool first = true;
      for (double x : values) {
        core::StrAppend(&out, first ? "" : " ", core::StrCat(x));
        first = false;
      }
      out.push_back('\n');
    };
    line({o.x(), o.y(), o.z()});
    line({1, 0, 0});
    line({0, 1, 0});
    line({0, 0, 1});
    line({1, 0, 0, 0});
    line({0, 1, 0, 0});
    line({0, 0, 1, 0});
    line({o.x(), o.y(), o.z(), 1});
    const auto colour = core::ColourChannels(cloud.attributes, cloud.size());
    const core::ScalarAttribute* intensity = nullptr;
    for (const core::ScalarAttribute& a : cloud.attributes) {
      if (a.name == "intensity" && a.values.size() == cloud.size()) intensity = &a;
    }
    for (size_t i = 0; i < cloud.size(); ++i) {
      const core::Vec3d p = cloud.positions[i].cast<double>() - o;
      std::vector<float> values = {static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()),
                                   intensity != nullptr ? intensity->values[i] : 0.5f};
      if (colour[0] != nullptr) {
        for (const core::ScalarAttribute* c : colour) values.push_back(c->values[i]);
      }
      for (size_t k = 0; k < values.size(); ++k) {
        if (k > 0) out.push_back(' ');
        internal::AppendFloat(out, values[k]);
      }
      out.push_back('\n');
    }
  }
  return out;
}

}  // namespace lsqsurf::io
