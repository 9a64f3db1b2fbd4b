#include "worker/io/pcd.h"

#include <lzf.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <optional>
#include <vector>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/text_scan.h"

namespace lsqsurf::io {
namespace {

using internal::LineReader;
using internal::NextToken;
using internal::ParseNumber;

constexpr size_t kMaxFields = 4096;         // Fields of a row (a descriptor has a few hundred values).
constexpr size_t kMaxRowBytes = 1 << 20;    // Bytes of a row.
constexpr uint64_t kMaxHeaderLines = 1000;  // Lines before DATA (comments included).
// LZF codes a run of at most 264 bytes in 3 bytes, so no block inflates past about 88 times
// its size: a header declaring more lies, and is refused before the buffer is allocated.
constexpr uint64_t kLzfMaxRatio = 90;

struct Field {
  std::string name;
  int size = 4;
  char type = 'F';
  uint64_t count = 1;
  size_t offset = 0;       // In a binary row.
  size_t first_value = 0;  // Its first value's place in an ascii row.
};

// One point as read, before it is kept or skipped.
struct Record {
  double position[3] = {0, 0, 0};
  double normal[3] = {0, 0, 0};
  uint32_t rgb = 0;
  std::vector<float> scalars;
};

double ReadBinary(const char* p, const Field& f) {
  auto as = [p]<typename T>(T) {
    T v;
    std::memcpy(&v, p, sizeof v);
    return static_cast<double>(v);
  };
  switch (f.type) {
    case 'F': return f.size == 4 ? as(float{}) : as(double{});
    case 'U':
      switch (f.size) {
        case 1: return as(uint8_t{});
        case 2: return as(uint16_t{});
        case 4: return as(uint32_t{});
        default: return as(uint64_t{});
      }
    default:
      switch (f.size) {
        case 1: return as(int8_t{});
        case 2: return as(int16_t{});
        case 4: return as(int32_t{});
        default: return as(int64_t{});
      }
  }
}

bool Finite3(const double (&v)[3]) { return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]); }

}  // namespace

struct PcdReader::State {
  std::string name;
  std::string_view bytes;
  PcdInfo info;
  std::vector<Field> fields;
  size_t row_bytes = 0;
  size_t row_values = 0;
  size_t data_begin = 0;
  int x = -1, y = -1, z = -1, nx = -1, ny = -1, nz = -1, rgb = -1;
  std::vector<int> scalars;  // Fields kept as attributes, in order.
  std::vector<std::string> scalar_names;
  bool with_normals = false;
  std::string inflated;              // binary_compressed: the block, each field's values together.
  std::vector<size_t> column_begin;  // binary_compressed: where each field's values start.
  std::optional<LineReader> lines;   // ascii: the rows after the header.
  uint64_t next = 0;                 // The next point to read.
  size_t consumed = 0;               // Bytes read past.

  absl::Status Error(std::string_view what) const { return absl::InvalidArgumentError(core::StrCat(name, ": ", what)); }

  absl::Status ParseHeader();
  absl::Status AssignRoles();
  absl::Status LocateData();
  absl::Status ReadRecord(Record& record);  // The point `next`, and moves past it.
  absl::Status ReadAsciiRecord(uint64_t point, Record& record);
  std::vector<std::string_view> tokens;  // ascii: the values of the row being read.
  absl::Status Rewind();
  absl::Status CheckNormals();
};

absl::Status PcdReader::State::ParseHeader() {
  LineReader reader(bytes);
  std::string_view line;
  std::vector<std::string_view> sizes, types, counts;
  std::optional<uint64_t> points;
  bool have_width = false, have_fields = false;
  while (true) {
    if (!reader.Next(line)) return Error("the header ends before its DATA line");
    if (reader.line_number() > kMaxHeaderLines) return Error("no DATA line in the first 1000 lines: not a PCD file");
    if (line.empty() || line.front() == '#') continue;
    std::string_view rest = line;
    const std::string_view key = NextToken(rest);
    std::vector<std::string_view> items;
    for (std::string_view t = NextToken(rest); !t.empty(); t = NextToken(rest)) {
      if (items.size() >= kMaxFields) return Error(core::StrCat("header line ", reader.line_number(), " is too long"));
      items.push_back(t);
    }
    const auto where = [&] { return core::StrCat("header line ", reader.line_number(), " (", key, ")"); };
    const auto one_count = [&](uint64_t& out) -> absl::Status {
      if (items.size() != 1 || !ParseNumber(items[0], out)) return Error(core::StrCat(where(), ": expected one count"));
      return absl::OkStatus();
    };
    if (key == "VERSION") continue;
    if (key == "FIELDS" || key == "COLUMNS") {
      if (items.empty()) return Error(core::StrCat(where(), ": no fields"));
      for (std::string_view n : items) fields.push_back(Field{.name = std::string(n)});
      have_fields = true;
    } else if (key == "SIZE") {
      sizes = items;
    } else if (key == "TYPE") {
      types = items;
    } else if (key == "COUNT") {
      counts = items;
    } else if (key == "WIDTH") {
      LSQSURF_RETURN_IF_ERROR(one_count(info.width));
      have_width = true;
    } else if (key == "HEIGHT") {
      LSQSURF_RETURN_IF_ERROR(one_count(info.height));
    } else if (key == "POINTS") {
      uint64_t n = 0;
      LSQSURF_RETURN_IF_ERROR(one_count(n));
      points = n;
    } else if (key == "VIEWPOINT") {
      if (items.size() != 7) return Error(core::StrCat(where(), ": expected tx ty tz qw qx qy qz"));
      for (size_t i = 0; i < 7; ++i) {
        if (!ParseNumber(items[i], info.viewpoint[i]) || !std::isfinite(info.viewpoint[i])) {
          return Error(core::StrCat(where(), ": '", items[i], "' is not a number"));
        }
      }
      info.has_viewpoint = true;
    } else if (key == "DATA") {
      if (items.size() != 1) return Error(core::StrCat(where(), ": expected ascii, binary or binary_compressed"));
      if (items[0] == "ascii") {
        info.encoding = PcdEncoding::kAscii;
      } else if (items[0] == "binary") {
        info.encoding = PcdEncoding::kBinary;
      } else if (items[0] == "binary_compressed") {
        info.encoding = PcdEncoding::kBinaryCompressed;
      } else {
        return Error(core::StrCat(where(), ": unknown encoding '", items[0], "' (ascii, binary or binary_compressed)"));
      }
      break;
    }
    // Other keys are not PCL's; like PCL, the reader passes over them.
  }
  data_begin = reader.offset() > bytes.size() ? bytes.size() : reader.offset();
  if (!have_fields) return Error("the header has no FIELDS line");
  if (sizes.size() != fields.size() || types.size() != fields.size() ||
      (!counts.empty() && counts.size() != fields.size())) {
    return Error(core::StrCat("the header names ", fields.size(), " fields but gives ", sizes.size(), " sizes, ",
                              types.size(), " types and ", counts.size(), " counts"));
  }
  for (size_t f = 0; f < fields.size(); ++f) {
    Field& field = fields[f];
    uint64_t size = 0;
    if (!ParseNumber(sizes[f], size) || (size != 1 && size != 2 && size != 4 && size != 8)) {
      return Error(core::StrCat("field ", field.name, ": size '", sizes[f], "' is not 1, 2, 4 or 8"));
    }
    field.size = static_cast<int>(size);
    if (types[f].size() != 1 || std::string_view("IUF").find(types[f][0]) == std::string_view::npos ||
        (types[f][0] == 'F' && size < 4)) {
      return Error(core::StrCat("field ", field.name, ": type '", types[f], "' with size ", size,
                                " is not one of I, U (1, 2, 4, 8 bytes) or F (4, 8)"));
    }
    field.type = types[f][0];
    if (!counts.empty() && (!ParseNumber(counts[f], field.count) || field.count == 0 || field.count > kMaxFields)) {
      return Error(core::StrCat("field ", field.name, ": count '", counts[f], "' is not 1..", kMaxFields));
    }
    field.offset = row_bytes;
    field.first_value = row_values;
    row_bytes += static_cast<size_t>(field.size) * field.count;
    row_values += field.count;
    if (row_bytes > kMaxRowBytes || row_values > kMaxFields) return Error("a point's fields take too many bytes");
  }
  if (!have_width) return Error("the header has no WIDTH line");
  if (info.height == 0 && info.width != 0) return Error("HEIGHT 0 with points in its rows");
  if (info.height != 0 && info.width > std::numeric_limits<uint64_t>::max() / info.height) {
    return Error("WIDTH times HEIGHT overflows");
  }
  info.points = points.value_or(info.width * info.height);
  if (info.points != info.width * info.height) {
    return Error(core::StrCat("POINTS ", info.points, " is not WIDTH ", info.width, " times HEIGHT ", info.height));
  }
  return AssignRoles();
}

// Which field is which: the position, normal and colour, and the scalars kept as attributes.
absl::Status PcdReader::State::AssignRoles() {
  for (size_t f = 0; f < fields.size(); ++f) {
    const Field& field = fields[f];
    const int index = static_cast<int>(f);
    const bool single = field.count == 1;
    auto role = [&](std::string_view n, int& slot) {
      if (field.name != n) return false;
      if (slot >= 0) return true;  // A repeated name: the first counts.
      if (single) slot = index;
      return true;
    };
    if (role("x", x) || role("y", y) || role("z", z) || role("normal_x", nx) || role("normal_y", ny) ||
        role("normal_z", nz)) {
      continue;
    }
    if ((field.name == "rgb" || field.name == "rgba") && single && field.size == 4) {
      if (rgb < 0) rgb = index;
      continue;
    }
    if (field.name == "_" || !single) continue;  // Padding, descriptors.
    scalars.push_back(index);
    scalar_names.push_back(field.name);
  }
  if (x < 0 || y < 0 || z < 0) return Error("the header has no single x, y and z fields");
  with_normals = nx >= 0 && ny >= 0 && nz >= 0;
  return absl::OkStatus();
}

absl::Status PcdReader::State::LocateData() {
  const size_t available = bytes.size() - data_begin;
  switch (info.encoding) {
    case PcdEncoding::kAscii: break;
    case PcdEncoding::kBinary:
      if (row_bytes != 0 && info.points > available / row_bytes) {
        return Error(core::StrCat("the header declares ", info.points, " points of ", row_bytes,
                                  " bytes but the data holds only ", available / row_bytes));
      }
      break;
    case PcdEncoding::kBinaryCompressed: {
      if (available < 8) return Error("the compressed data has no sizes");
      uint32_t packed = 0, unpacked = 0;
      std::memcpy(&packed, bytes.data() + data_begin, 4);
      std::memcpy(&unpacked, bytes.data() + data_begin + 4, 4);
      if (packed > available - 8) {
        return Error(core::StrCat("the compressed block claims ", packed, " bytes; the file holds ", available - 8));
      }
      if (static_cast<uint64_t>(row_bytes) * info.points != unpacked) {
        return Error(core::StrCat("the compressed block inflates to ", unpacked, " bytes, but ", info.points,
                                  " points of ", row_bytes, " bytes take ", row_bytes * info.points));
      }
      if (unpacked > kLzfMaxRatio * uint64_t{packed} + 64) {
        return Error(core::StrCat("the compressed block of ", packed, " bytes claims to inflate to ", unpacked,
                                  ", more than LZF can"));
      }
      inflated.resize(unpacked);
      if (unpacked > 0) {
        const unsigned got = lzf_decompress(bytes.data() + data_begin + 8, packed, inflated.data(), unpacked);
        if (got != unpacked) {
          return Error(core::StrCat("the compressed block does not inflate to its declared ", unpacked, " bytes",
                                    got == 0 ? " (it is damaged or inflates past them)" : ""));
        }
      }
      size_t begin = 0;
      for (const Field& f : fields) {
        column_begin.push_back(begin);
        begin += static_cast<size_t>(f.size) * f.count * info.points;
      }
      consumed = data_begin + 8 + packed;
      break;
    }
  }
  return Rewind();
}

absl::Status PcdReader::State::Rewind() {
  next = 0;
  info.skipped_points = 0;
  if (info.encoding == PcdEncoding::kAscii) lines.emplace(bytes.substr(data_begin));
  if (info.encoding != PcdEncoding::kBinaryCompressed) consumed = data_begin;
  return absl::OkStatus();
}

absl::Status PcdReader::State::ReadAsciiRecord(uint64_t point, Record& record) {
  std::string_view line;
  do {
    if (!lines->Next(line)) {
      return Error(core::StrCat("the data ends after ", point, " of the ", info.points, " points the header declares"));
    }
  } while (line.find_first_not_of(" \t") == std::string_view::npos);
  consumed = data_begin + lines->offset();
  tokens.clear();
  for (std::string_view t = NextToken(line); !t.empty() && tokens.size() < row_values; t = NextToken(line)) {
    tokens.push_back(t);
  }
  if (tokens.size() != row_values || !NextToken(line).empty()) {
    return Error(core::StrCat("point ", point, " (data line ", lines->line_number(), ") has ",
                              tokens.size() == row_values ? "more" : std::to_string(tokens.size()), " values, not ",
                              row_values));
  }
  absl::Status bad = absl::OkStatus();
  auto value = [&](int f) {
    double v = 0;
    const Field& field = fields[static_cast<size_t>(f)];
    const std::string_view t = tokens[field.first_value];
    if (!ParseNumber(t, v) && bad.ok()) {
      bad = Error(core::StrCat("point ", point, ": '", t.substr(0, 40), "' in field ", field.name, " is not a number"));
    }
    return v;
  };
  const int position[3] = {x, y, z}, normal[3] = {nx, ny, nz};
  for (int i = 0; i < 3; ++i) record.position[i] = value(position[i]);
  if (with_normals) {
    for (int i = 0; i < 3; ++i) record.normal[i] = value(normal[i]);
  }
  if (rgb >= 0) {
    // PCL writes a packed F colour as the float its bits make, and a U one as the integer.
    if (const Field& field = fields[static_cast<size_t>(rgb)]; field.type == 'F') {
      float v = 0;
      record.rgb = ParseNumber(tokens[field.first_value], v) ? std::bit_cast<uint32_t>(v) : 0;
    } else {
      const double v = value(rgb);
      record.rgb = v >= 0 && v <= 4294967295.0 ? static_cast<uint32_t>(v) : 0;
    }
  }
  for (size_t s = 0; s < scalars.size(); ++s) record.scalars[s] = static_cast<float>(value(scalars[s]));
  return bad;
}

absl::Status PcdReader::State::ReadRecord(Record& record) {
  record.scalars.resize(scalars.size());
  const uint64_t point = next++;
  if (info.encoding == PcdEncoding::kAscii) return ReadAsciiRecord(point, record);
  auto at = [&](int f) -> const char* {
    const Field& field = fields[static_cast<size_t>(f)];
    if (info.encoding == PcdEncoding::kBinary) {
      return bytes.data() + data_begin + point * row_bytes + field.offset;
    }
    return inflated.data() + column_begin[static_cast<size_t>(f)] + point * field.count * field.size;
  };
  if (info.encoding == PcdEncoding::kBinary) consumed = data_begin + (point + 1) * row_bytes;
  const int position[3] = {x, y, z}, normal[3] = {nx, ny, nz};
  for (int i = 0; i < 3; ++i)
    record.position[i] = ReadBinary(at(position[i]), fields[static_cast<size_t>(position[i])]);
  if (with_normals) {
    for (int i = 0; i < 3; ++i) record.normal[i] = ReadBinary(at(normal[i]), fields[static_cast<size_t>(normal[i])]);
  }
  if (rgb >= 0) std::memcpy(&record.rgb, at(rgb), 4);
  for (size_t s = 0; s < scalars.size(); ++s) {
    record.scalars[s] = static_cast<float>(ReadBinary(at(scalars[s]), fields[static_cast<size_t>(scalars[s])]));
  }
  return absl::OkStatus();
}

// PCL leaves a NaN normal where it could not estimate one; the cloud then goes without normals,
// to be estimated whole, rather than with holes in them.
absl::Status PcdReader::State::CheckNormals() {
  if (!with_normals) return absl::OkStatus();
  Record record;
  while (next < info.points) {
    LSQSURF_RETURN_IF_ERROR(ReadRecord(record));
    if (Finite3(record.position) && !Finite3(record.normal)) {
      with_normals = false;
      info.normals_dropped = true;
      break;
    }
  }
  return Rewind();
}

PcdReader::PcdReader(std::unique_ptr<State> state) : state_(std::move(state)) {}
PcdReader::~PcdReader() = default;

absl::StatusOr<std::unique_ptr<PcdReader>> PcdReader::Open(std::string_view bytes, std::string name) {
  auto state = std::make_unique<State>();
  state->name = std::move(name);
  state->bytes = bytes;
  LSQSURF_RETURN_IF_ERROR(state->ParseHeader());
  LSQSURF_RETURN_IF_ERROR(state->LocateData());
  LSQSURF_RETURN_IF_ERROR(state->CheckNormals());
  return std::unique_ptr<PcdReader>(new PcdReader(std::move(state)));
}

const PcdInfo& PcdReader::info() const { return state_->info; }
size_t PcdReader::offset() const { return state_->consumed; }

absl::Status PcdReader::Read(size_t max_points, core::PointCloud& cloud) {
  State& s = *state_;
  const bool colour = s.rgb >= 0;
  if (cloud.attributes.empty()) {
    if (colour) {
      for (const char* n : core::kColourChannels) cloud.attributes.push_back({n, {}});
    }
    for (const std::string& n : s.scalar_names) cloud.attributes.push_back({n, {}});
  }
  Record record;
  for (size_t kept = 0; kept < max_points && s.next < s.info.points;) {
    LSQSURF_RETURN_IF_ERROR(s.ReadRecord(record));
    if (!Finite3(record.position)) {
      ++s.info.skipped_points;
      continue;
    }
    ++kept;
    cloud.positions.emplace_back(static_cast<float>(record.position[0]), static_cast<float>(record.position[1]),
                                 static_cast<float>(record.position[2]));
    if (s.with_normals) {
      core::Vec3f n(static_cast<float>(record.normal[0]), static_cast<float>(record.normal[1]),
                    static_cast<float>(record.normal[2]));
      if (n.norm() > 0) n.normalize();
      cloud.normals.push_back(n);
    }
    size_t a = 0;
    if (colour) {
      for (int shift : {16, 8, 0})
        cloud.attributes[a++].values.push_back(static_cast<float>((record.rgb >> shift) & 255));
    }
    for (float v : record.scalars) cloud.attributes[a++].values.push_back(v);
  }
  return absl::OkStatus();
}

absl::StatusOr<core::PointCloud> ParsePcd(std::string_view bytes, std::string_view name, PcdInfo* info) {
  auto reader = PcdReader::Open(bytes, std::string(name));
  if (!reader.ok()) return reader.status();
  core::PointCloud cloud;
  LSQSURF_RETURN_IF_ERROR((*reader)->Read(std::numeric_limits<size_t>::max(), cloud));
  if (info != nullptr) *info = (*reader)->info();
  return cloud;
}

std::string EncodePcd(const core::PointCloud& cloud, PcdEncoding encoding, const std::array<double, 7>& viewpoint) {
  struct Column {
    std::string name;
    char type;
    std::function<float(size_t)> value;  // For rgb: the packed bits as a float, as PCL keeps them.
  };
  std::vector<Column> columns;
  for (int i = 0; i < 3; ++i) {
    columns.push_back({std::string(1, "xyz"[i]), 'F', [&cloud, i](size_t p) { return cloud.positions[p][i]; }});
  }
  if (cloud.has_normals()) {
    for (int i = 0; i < 3; ++i) {
      columns.push_back({core::StrCat("normal_", std::string(1, "xyz"[i])), 'F',
                         [&cloud, i](size_t p) { return cloud.normals[p][i]; }});
    }
  }
  const auto channel = core::ColourChannels(cloud.attributes, cloud.size());
  const bool colour = channel[0] != nullptr;
  if (colour) {
    columns.push_back(
        {"rgb", 'F', [channel](size_t p) { return std::bit_cast<float>(core::PackedColour(channel, p)); }});
  }
  for (const core::ScalarAttribute& a : cloud.attributes) {
    if (colour && (&a == channel[0] || &a == channel[1] || &a == channel[2])) continue;
    columns.push_back({a.name, 'F', [&a](size_t p) { return a.values[p]; }});
  }
  const size_t n = cloud.size();
  std::string out = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS";
  for (const Column& c : columns) core::StrAppend(&out, " ", c.name);
  out += "\nSIZE";
  for (size_t c = 0; c < columns.size(); ++c) out += " 4";
  out += "\nTYPE";
  for (size_t c = 0; c < columns.size(); ++c) out += " F";
  out += "\nCOUNT";
  for (size_t c = 0; c < columns.size(); ++c) out += " 1";
  core::StrAppend(&out, "\nWIDTH ", n, "\nHEIGHT 1\nVIEWPOINT");
  for (double v : viewpoint) {
    out.push_back(' ');
    internal::AppendFloat(out, static_cast<float>(v));
  }
  const char* names[] = {"ascii", "binary", "binary_compressed"};
  core::StrAppend(&out, "\nPOINTS ", n, "\nDATA ", names[static_cast<int>(encoding)], "\n");
  if (encoding == PcdEncoding::kAscii) {
    for (size_t p = 0; p < n; ++p) {
      for (size_t c = 0; c < columns.size(); ++c) {
        if (c > 0) out.push_back(' ');
        internal::AppendFloat(out, columns[c].value(p));
      }
      out.push_back('\n');
    }
    return out;
  }
  std::string block(n * columns.size() * 4, '\0');
  for (size_t c = 0; c < columns.size(); ++c) {
    for (size_t p = 0; p < n; ++p) {
      const float v = columns[c].value(p);
      // binary: a row per point; compressed: a column per field.
      const size_t at = encoding == PcdEncoding::kBinary ? (p * columns.size() + c) * 4 : (c * n + p) * 4;
      std::memcpy(block.data() + at, &v, 4);
    }
  }
  if (encoding == PcdEncoding::kBinary) return out + block;
  std::string packed(block.size() + block.size() / 16 + 64, '\0');
  const unsigned size = block.empty() ? 0
                                      : lzf_compress(block.data(), static_cast<unsigned>(block.size()), packed.data(),
                                                     static_cast<unsigned>(packed.size()));
  const uint32_t sizes[2] = {size, static_cast<uint32_t>(block.size())};
  out.append(reinterpret_cast<const char*>(sizes), 8);
  out.append(packed.data(), size);
  return out;
}

}  // namespace lsqsurf::io
