#include <algorithm>
#include <bit>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <span>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/volume_cells.h"
#include "worker/io/volume_formats.h"
#include "worker/io/vtk_grid.h"

namespace lsqsurf::io {
namespace {

using core::Vec3d;
using core::Vec3f;
using core::VertexField;
using core::VolumeMesh;

int TypeSize(std::string_view type) {
  if (type == "unsigned_char" || type == "char") return 1;
  if (type == "unsigned_short" || type == "short") return 2;
  if (type == "unsigned_int" || type == "int" || type == "float" || type == "vtktypeint32" || type == "vtktypeuint32") {
    return 4;
  }
  if (type == "unsigned_long" || type == "long" || type == "double" || type == "vtktypeint64" ||
      type == "vtktypeuint64") {
    return 8;
  }
  return 0;
}

template <class T>
double LoadBigEndian(const char* p) {
  T v;
  std::memcpy(&v, p, sizeof(T));
  if constexpr (std::endian::native == std::endian::little && sizeof(T) > 1) {
    using U = std::conditional_t<sizeof(T) == 2, uint16_t, std::conditional_t<sizeof(T) == 4, uint32_t, uint64_t>>;
    U u;
    std::memcpy(&u, &v, sizeof(T));
    if constexpr (sizeof(T) == 2) u = static_cast<U>((u >> 8) | (u << 8));
    if constexpr (sizeof(T) == 4) u = __builtin_bswap32(u);
    if constexpr (sizeof(T) == 8) u = __builtin_bswap64(u);
    std::memcpy(&v, &u, sizeof(T));
  }
  return static_cast<double>(v);
}

double LoadBinary(std::string_view type, const char* p) {
  if (type == "unsigned_char") return LoadBigEndian<uint8_t>(p);
  if (type == "char") return LoadBigEndian<int8_t>(p);
  if (type == "unsigned_short") return LoadBigEndian<uint16_t>(p);
  if (type == "short") return LoadBigEndian<int16_t>(p);
  if (type == "unsigned_int" || type == "vtktypeuint32") return LoadBigEndian<uint32_t>(p);
  if (type == "int" || type == "vtktypeint32") return LoadBigEndian<int32_t>(p);
  if (type == "float") return LoadBigEndian<float>(p);
  if (type == "double") return LoadBigEndian<double>(p);
  if (type == "unsigned_long" || type == "vtktypeuint64") return LoadBigEndian<uint64_t>(p);
  return LoadBigEndian<int64_t>(p);
}

// Tokens of the text parts and the numbers of the data blocks, ASCII or big-endian binary.
constexpr int64_t kMaxCount = (int64_t{1} << 31) - 1;  // Any count in a legacy VTK file.

class VtkCursor {
 public:
  VtkCursor(std::string_view bytes, std::string_view name) : b_(bytes), name_(name) {}

  void set_binary(bool binary) { binary_ = binary; }
  bool AtEnd() {
    SkipSpace();
    return pos_ >= b_.size();
  }
  absl::StatusOr<std::string_view> Token(std::string_view what) {
    SkipSpace();
    const size_t start = pos_;
    while (pos_ < b_.size() && !IsSpace(b_[pos_])) ++pos_;
    if (pos_ == start) return Error(core::StrCat("expected ", what, " but the file ends"));
    return b_.substr(start, pos_ - start);
  }
  absl::StatusOr<int64_t> Count(std::string_view what) {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view tok, Token(what));
    int64_t v = 0;
    auto [p, ec] = std::from_chars(tok.data(), tok.data() + tok.size(), v);
    if (ec != std::errc() || p != tok.data() + tok.size() || v < 0) {
      return Error(core::StrCat("expected ", what, " (a count), found '", tok, "'"));
    }
    // Counts are multiplied together (components × tuples, entries × 4): bounding each keeps
    // those products far from overflow, and no file holds 2^31 of anything.
    if (v > kMaxCount) return Error(core::StrCat(what, " ", v, " is too large (at most ", kMaxCount, ")"));
    return v;
  }
  absl::StatusOr<double> Number(std::string_view what) {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view tok, Token(what));
    return ParseNumber(tok, what);
  }
  // The rest of the current line (for the header lines).
  std::string_view Line() {
    const size_t start = pos_;
    while (pos_ < b_.size() && b_[pos_] != '\n') ++pos_;
    std::string_view line = b_.substr(start, pos_ - start);
    if (pos_ < b_.size()) ++pos_;
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    return line;
  }
  // Skips lines up to and including the next empty one (VTK 5's METADATA blocks).
  void SkipBlock() {
    Line();
    while (pos_ < b_.size() && !Line().empty()) {
    }
  }
  // `count` values of VTK type `type` for section `what`.
  absl::Status Values(std::string_view type, int64_t count, std::string_view what, std::vector<double>& out) {
    const int size = TypeSize(type);
    if (size == 0) return Error(core::StrCat(what, ": data type '", type, "' is not supported"));
    const size_t left = b_.size() - std::min(pos_, b_.size());
    // Each ASCII number needs at least two bytes (a digit and a separator).
    // Checked before the multiplication, which could otherwise wrap: every value takes a byte at least.
    const bool fits = count >= 0 && static_cast<uint64_t>(count) <= left + 1 &&
                      (binary_ ? static_cast<uint64_t>(count) * size : static_cast<uint64_t>(count)) <= left + 1;
    if (!fits) {
      return Error(
          core::StrCat(what, ": ", count, " values do not fit in the ", left, " bytes left (truncated file?)"));
    }
    out.resize(static_cast<size_t>(count));
    if (!binary_) {
      for (int64_t i = 0; i < count; ++i) {
        if (AtEnd()) return Error(core::StrCat(what, ": the data is truncated: ", i, " of ", count, " values"));
        LSQSURF_ASSIGN_OR_RETURN(std::string_view tok, Token(what));
        LSQSURF_ASSIGN_OR_RETURN(out[static_cast<size_t>(i)], ParseNumber(tok, what));
      }
      return absl::OkStatus();
    }
    // Binary data starts after the end of the header line.
    while (pos_ < b_.size() && (b_[pos_] == ' ' || b_[pos_] == '\t' || b_[pos_] == '\r')) ++pos_;
    if (pos_ < b_.size() && b_[pos_] == '\n') ++pos_;
    if (static_cast<uint64_t>(count) * size > b_.size() - pos_) {
      return Error(core::StrCat(what, ": ", count, " binary values need ", static_cast<uint64_t>(count) * size,
                                " bytes, only ", b_.size() - pos_, " are left (truncated file?)"));
    }
    for (int64_t i = 0; i < count; ++i) out[i] = LoadBinary(type, b_.data() + pos_ + i * size);
    pos_ += static_cast<size_t>(count) * size;
    return absl::OkStatus();
  }
  absl::Status Error(std::string_view message) const {
    return absl::InvalidArgumentError(core::StrCat(name_, ": ", message));
  }

 private:
  static bool IsSpace(char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r'; }
  void SkipSpace() {
    while (pos_ < b_.size() && IsSpace(b_[pos_])) ++pos_;
  }
  absl::StatusOr<double> ParseNumber(std::string_view tok, std::string_view what) const {
    double v = 0;
    auto [p, ec] = std::from_chars(tok.data(), tok.data() + tok.size(), v);
    if (ec != std::errc() || p != tok.data() + tok.size()) {
      // VTK writes non-finite values as nan / inf; they are read and refused later by name.
      if (tok == "nan" || tok == "NaN" || tok == "-nan") return std::numeric_limits<double>::quiet_NaN();
      if (tok == "inf" || tok == "Infinity") return std::numeric_limits<double>::infinity();
      if (tok == "-inf" || tok == "-Infinity") return -std::numeric_limits<double>::infinity();
      return Error(core::StrCat(what, ": '", tok, "' is not a number"));
    }
    return v;
  }

  std::string_view b_;
  std::string_view name_;
  size_t pos_ = 0;
  bool binary_ = false;
};

// The sections of a file, before they become a mesh.
struct VtkContent {
  std::string dataset;
  std::vector<double> points;
  std::array<int64_t, 3> dimensions = {0, 0, 0};
  Vec3d origin = Vec3d::Zero(), spacing = Vec3d::Ones();
  std::array<std::vector<double>, 3> axes;  // RECTILINEAR_GRID coordinates.
  std::vector<double> cells, offsets, cell_types;
  bool cells_with_offsets = false;  // Version 5 layout: OFFSETS + CONNECTIVITY.
  int64_t point_count = -1;         // From POINT_DATA.
  std::vector<VertexField> fields;
  // Velocity grids: the first VECTORS array of the point data, kept in double precision, and
  // the most points the data may have (a bound on what is read before the grid is checked).
  bool keep_vectors = false;
  std::vector<double> vectors;
  int64_t max_points = kMaxCount;
};

absl::Status ReadPointArray(VtkCursor& c, VtkContent& v, std::string name, std::string_view type, int components,
                            bool into_fields) {
  std::vector<double> values;
  const int64_t n = std::max<int64_t>(0, v.point_count);
  LSQSURF_RETURN_IF_ERROR(c.Values(type, n * components, core::StrCat("array '", name, "'"), values));
  if (!into_fields) return absl::OkStatus();
  VertexField f{std::move(name), components, std::vector<float>(values.begin(), values.end())};
  v.fields.push_back(std::move(f));
  return absl::OkStatus();
}

// One attribute section (SCALARS, VECTORS, FIELD, ...); `keep` is false inside CELL_DATA.
absl::Status ReadAttribute(VtkCursor& c, VtkContent& v, std::string_view key, bool keep) {
  std::vector<double> skip;
  if (key == "SCALARS") {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view name, c.Token("the array name"));
    LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
    const std::string array_name(name);
    // Optional component count, then an optional LOOKUP_TABLE line.
    LSQSURF_ASSIGN_OR_RETURN(std::string_view next, c.Token("LOOKUP_TABLE or values"));
    int components = 1;
    if (next != "LOOKUP_TABLE" &&
        std::all_of(next.begin(), next.end(), [](char ch) { return ch >= '0' && ch <= '9'; })) {
      components = std::clamp(std::atoi(std::string(next).c_str()), 1, 4);
      LSQSURF_ASSIGN_OR_RETURN(next, c.Token("LOOKUP_TABLE"));
    }
    if (next != "LOOKUP_TABLE") return c.Error(core::StrCat("SCALARS ", array_name, ": expected LOOKUP_TABLE"));
    LSQSURF_RETURN_IF_ERROR(c.Token("the lookup table name").status());
    return ReadPointArray(c, v, array_name, type, components, keep);
  }
  if (key == "VECTORS" || key == "NORMALS" || key == "TENSORS") {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view name, c.Token("the array name"));
    LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
    if (key == "VECTORS" && keep && v.keep_vectors && v.vectors.empty()) {
      return c.Values(type, std::max<int64_t>(0, v.point_count) * 3, core::StrCat("VECTORS ", name), v.vectors);
    }
    return ReadPointArray(c, v, std::string(name), type, key == "TENSORS" ? 9 : 3, keep);
  }
  if (key == "TEXTURE_COORDINATES") {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view name, c.Token("the array name"));
    LSQSURF_ASSIGN_OR_RETURN(int64_t dim, c.Count("the dimension"));
    LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
    return ReadPointArray(c, v, std::string(name), type, static_cast<int>(std::clamp<int64_t>(dim, 1, 3)), keep);
  }
  if (key == "COLOR_SCALARS") {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view name, c.Token("the array name"));
    LSQSURF_ASSIGN_OR_RETURN(int64_t m, c.Count("the component count"));
    return ReadPointArray(c, v, std::string(name), "unsigned_char", static_cast<int>(std::clamp<int64_t>(m, 1, 4)),
                          false);
  }
  if (key == "LOOKUP_TABLE") {
    LSQSURF_RETURN_IF_ERROR(c.Token("the table name").status());
    LSQSURF_ASSIGN_OR_RETURN(int64_t size, c.Count("the table size"));
    return c.Values("unsigned_char", size * 4, "LOOKUP_TABLE", skip);
  }
  if (key == "FIELD") {
    LSQSURF_RETURN_IF_ERROR(c.Token("the field name").status());
    LSQSURF_ASSIGN_OR_RETURN(int64_t arrays, c.Count("the number of arrays"));
    for (int64_t a = 0; a < arrays; ++a) {
      LSQSURF_ASSIGN_OR_RETURN(std::string_view name, c.Token("an array name"));
      if (name == "METADATA") {
        c.SkipBlock();
        --a;
        continue;
      }
      const std::string array_name(name);
      LSQSURF_ASSIGN_OR_RETURN(int64_t components, c.Count("the component count"));
      LSQSURF_ASSIGN_OR_RETURN(int64_t tuples, c.Count("the tuple count"));
      LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
      if (keep && tuples == v.point_count && components >= 1 && components <= 9) {
        LSQSURF_RETURN_IF_ERROR(ReadPointArray(c, v, array_name, type, static_cast<int>(components), true));
      } else {
        LSQSURF_RETURN_IF_ERROR(c.Values(type, components * tuples, core::StrCat("array '", array_name, "'"), skip));
      }
    }
    return absl::OkStatus();
  }
  return c.Error(core::StrCat("unknown section '", key, "'"));
}

absl::Status ReadSections(VtkCursor& c, VtkContent& v, bool version5) {
  bool in_cell_data = false;
  std::vector<double> skip;
  while (!c.AtEnd()) {
    LSQSURF_ASSIGN_OR_RETURN(std::string_view key, c.Token("a section"));
    if (key == "POINTS") {
      LSQSURF_ASSIGN_OR_RETURN(int64_t n, c.Count("the point count"));
      LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
      LSQSURF_RETURN_IF_ERROR(c.Values(type, 3 * n, "POINTS", v.points));
    } else if (key == "DIMENSIONS") {
      for (int a = 0; a < 3; ++a) {
        LSQSURF_ASSIGN_OR_RETURN(v.dimensions[a], c.Count("a dimension"));
      }
    } else if (key == "ORIGIN" || key == "SPACING" || key == "ASPECT_RATIO") {
      Vec3d& target = key == "ORIGIN" ? v.origin : v.spacing;
      for (int a = 0; a < 3; ++a) {
        LSQSURF_ASSIGN_OR_RETURN(target[a], c.Number(key));
      }
    } else if (key == "X_COORDINATES" || key == "Y_COORDINATES" || key == "Z_COORDINATES") {
      LSQSURF_ASSIGN_OR_RETURN(int64_t n, c.Count("the coordinate count"));
      LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
      LSQSURF_RETURN_IF_ERROR(c.Values(type, n, key, v.axes[key[0] - 'X']));
    } else if (key == "CELLS") {
      LSQSURF_ASSIGN_OR_RETURN(int64_t n, c.Count("the cell count"));
      LSQSURF_ASSIGN_OR_RETURN(int64_t size, c.Count("the connectivity size"));
      if (version5) {
        v.cells_with_offsets = true;
        const std::array<std::tuple<std::string_view, std::vector<double>*, int64_t>, 2> parts = {
            std::tuple{"OFFSETS", &v.offsets, n}, std::tuple{"CONNECTIVITY", &v.cells, size}};
        for (const auto& [label, target, count] : parts) {
          LSQSURF_ASSIGN_OR_RETURN(std::string_view tag, c.Token(label));
          if (tag != label) return c.Error(core::StrCat("CELLS: expected ", label, ", found '", tag, "'"));
          LSQSURF_ASSIGN_OR_RETURN(std::string_view type, c.Token("the data type"));
          LSQSURF_RETURN_IF_ERROR(c.Values(type, count, label, *target));
        }
      } else {
        LSQSURF_RETURN_IF_ERROR(c.Values("int", size, "CELLS", v.cells));
      }
    } else if (key == "CELL_TYPES") {
      LSQSURF_ASSIGN_OR_RETURN(int64_t n, c.Count("the cell count"));
      LSQSURF_RETURN_IF_ERROR(c.Values("int", n, "CELL_TYPES", v.cell_types));
    } else if (key == "POINT_DATA" || key == "CELL_DATA") {
      LSQSURF_ASSIGN_OR_RETURN(int64_t n, c.Count("the count"));
      in_cell_data = key == "CELL_DATA";
      // In double: three dimensions of up to 2^31 overflow 64 bits.
      const double grid_points = static_cast<double>(v.dimensions[0]) * static_cast<double>(v.dimensions[1]) *
                                 static_cast<double>(v.dimensions[2]);
      if (!in_cell_data && grid_points > static_cast<double>(v.max_points)) {
        return c.Error(core::StrCat("the grid has more than ", v.max_points, " points (DIMENSIONS ", v.dimensions[0],
                                    " ", v.dimensions[1], " ", v.dimensions[2], "); at most that many are accepted"));
      }
      if (!in_cell_data && v.dataset != "UNSTRUCTURED_GRID" && grid_points > 0 &&
          static_cast<double>(n) != grid_points) {
        return c.Error(core::StrCat("POINT_DATA ", n, ": it must equal nx·ny·nz = ", grid_points));
      }
      if (!in_cell_data && n > v.max_points) {
        return c.Error(core::StrCat("POINT_DATA ", n, " is more than the ", v.max_points, " points accepted"));
      }
      if (!in_cell_data) v.point_count = n;
      if (in_cell_data) v.point_count = -n - 1;  // Arrays of n tuples, skipped.
    } else if (key == "METADATA") {
      c.SkipBlock();
    } else {
      const int64_t saved = v.point_count;
      if (in_cell_data) v.point_count = -saved - 1;
      absl::Status s = ReadAttribute(c, v, key, !in_cell_data);
      v.point_count = saved;
      LSQSURF_RETURN_IF_ERROR(s);
    }
  }
  return absl::OkStatus();
}

absl::Status CheckedIndex(VtkCursor& c, double value, std::string_view what, uint32_t& out) {
  if (!(value >= 0 && value < 4294967295.0) || value != std::floor(value)) {
    return c.Error(core::StrCat(what, ": ", value, " is not a valid index"));
  }
  out = static_cast<uint32_t>(value);
  return absl::OkStatus();
}

// CELLS and CELL_TYPES into the mesh's cell arrays.
absl::Status AssembleCells(VtkCursor& c, const VtkContent& v, VolumeMesh& mesh) {
  const size_t n = v.cell_types.size();
  std::vector<uint32_t> vertices;
  size_t pos = 0;
  if (v.cells_with_offsets && v.offsets.size() != n + 1) {
    return c.Error(core::StrCat("CELLS has ", v.offsets.size(), " offsets for ", n, " cell types (need one more)"));
  }
  for (size_t cell = 0; cell < n; ++cell) {
    size_t begin = 0, end = 0;
    if (v.cells_with_offsets) {
      // Clamped before the cast: a hostile offset may be any double.
      const double limit = static_cast<double>(v.cells.size()) + 1;
      begin = static_cast<size_t>(std::clamp(v.offsets[cell], 0.0, limit));
      end = static_cast<size_t>(std::clamp(v.offsets[cell + 1], 0.0, limit));
    } else {
      if (pos >= v.cells.size()) return c.Error(core::StrCat("CELLS ends before cell ", cell, " of ", n));
      begin = pos + 1;
      end = begin + static_cast<size_t>(std::clamp(v.cells[pos], 0.0, static_cast<double>(v.cells.size())));
      pos = end;
    }
    if (end < begin || end > v.cells.size()) {
      return c.Error(core::StrCat("CELLS: cell ", cell, " runs past the end of the connectivity"));
    }
    vertices.resize(end - begin);
    for (size_t k = begin; k < end; ++k) {
      LSQSURF_RETURN_IF_ERROR(CheckedIndex(c, v.cells[k], core::StrCat("CELLS: cell ", cell), vertices[k - begin]));
    }
    AppendCell(CellKind(v.cell_types[cell]), vertices, mesh);
  }
  return absl::OkStatus();
}

absl::StatusOr<VolumeMesh> BuildMesh(VtkCursor& c, VtkContent& v) {
  VolumeMesh mesh;
  const auto& d = v.dimensions;
  const bool structured = v.dataset != "UNSTRUCTURED_GRID";
  if (structured && (d[0] < 1 || d[1] < 1 || d[2] < 1)) return c.Error(core::StrCat(v.dataset, " without DIMENSIONS"));
  const int64_t grid_points = d[0] * d[1] * d[2];
  if (v.dataset == "STRUCTURED_POINTS" || v.dataset == "RECTILINEAR_GRID") {
    if (v.dataset == "RECTILINEAR_GRID") {
      for (int a = 0; a < 3; ++a) {
        if (static_cast<int64_t>(v.axes[a].size()) != d[a]) {
          return c.Error(core::StrCat("RECTILINEAR_GRID: ", static_cast<char>('X' + a), "_COORDINATES has ",
                                      v.axes[a].size(), " values for dimension ", d[a]));
        }
      }
    }
    mesh.positions.reserve(static_cast<size_t>(grid_points));
    for (int64_t k = 0; k < d[2]; ++k) {
      for (int64_t j = 0; j < d[1]; ++j) {
        for (int64_t i = 0; i < d[0]; ++i) {
          const Vec3d p =
              v.dataset == "RECTILINEAR_GRID"
                  ? Vec3d(v.axes[0][i], v.axes[1][j], v.axes[2][k])
                  : Vec3d(v.origin + Vec3d(static_cast<double>(i), static_cast<double>(j), static_cast<double>(k))
                                         .cwiseProduct(v.spacing));
          mesh.positions.push_back(p.cast<float>());
        }
      }
    }
  } else {
    if (v.points.empty()) return c.Error(core::StrCat(v.dataset, " without POINTS"));
    mesh.positions.resize(v.points.size() / 3);
    for (size_t i = 0; i < mesh.positions.size(); ++i) {
      mesh.positions[i] = Vec3d(v.points[3 * i], v.points[3 * i + 1], v.points[3 * i + 2]).cast<float>();
    }
    if (v.dataset == "STRUCTURED_GRID" && static_cast<int64_t>(mesh.positions.size()) != grid_points) {
      return c.Error(core::StrCat("STRUCTURED_GRID: ", mesh.positions.size(), " points for dimensions ", d[0], " x ",
                                  d[1], " x ", d[2]));
    }
  }
  if (structured) {
    core::AddStructuredHexahedra(mesh, static_cast<int>(d[0]), static_cast<int>(d[1]), static_cast<int>(d[2]));
  } else if (!v.cell_types.empty()) {
    LSQSURF_RETURN_IF_ERROR(AssembleCells(c, v, mesh));
  }
  for (VertexField& f : v.fields) {
    if (f.values.size() != mesh.positions.size() * f.components) {
      return c.Error(
          core::StrCat("POINT_DATA has ", v.point_count, " values per array for ", mesh.positions.size(), " points"));
    }
    mesh.fields.push_back(std::move(f));
  }
  return mesh;
}

// The header up to the dataset's type (in `v`); whether the file is of version 5.
absl::StatusOr<bool> ReadHeader(VtkCursor& c, VtkContent& v) {
  const std::string_view magic = c.Line();
  if (magic.rfind("# vtk DataFile Version", 0) != 0) {
    return c.Error("not a legacy VTK file (the first line must be '# vtk DataFile Version x.y')");
  }
  const bool version5 = magic.find("Version 5") != std::string_view::npos;
  c.Line();  // Title.
  std::string_view format = c.Line();
  while (!format.empty() && (format.back() == ' ' || format.back() == '\t')) format.remove_suffix(1);
  if (format != "ASCII" && format != "BINARY") {
    return c.Error(core::StrCat("the third line must be ASCII or BINARY, found '", format, "'"));
  }
  c.set_binary(format == "BINARY");
  LSQSURF_ASSIGN_OR_RETURN(std::string_view dataset_key, c.Token("DATASET"));
  if (dataset_key != "DATASET") return c.Error(core::StrCat("expected DATASET, found '", dataset_key, "'"));
  LSQSURF_ASSIGN_OR_RETURN(std::string_view dataset, c.Token("the dataset type"));
  v.dataset = std::string(dataset);
  return version5;
}

}  // namespace

absl::StatusOr<VolumeMesh> ParseLegacyVtk(std::string_view bytes, std::string_view name) {
  VtkCursor c(bytes, name);
  VtkContent v;
  LSQSURF_ASSIGN_OR_RETURN(const bool version5, ReadHeader(c, v));
  if (v.dataset != "UNSTRUCTURED_GRID" && v.dataset != "STRUCTURED_GRID" && v.dataset != "STRUCTURED_POINTS" &&
      v.dataset != "RECTILINEAR_GRID") {
    return c.Error(core::StrCat("dataset ", v.dataset,
                                " holds no volume; use UNSTRUCTURED_GRID, STRUCTURED_GRID, STRUCTURED_POINTS or "
                                "RECTILINEAR_GRID"));
  }
  LSQSURF_RETURN_IF_ERROR(ReadSections(c, v, version5));
  LSQSURF_ASSIGN_OR_RETURN(VolumeMesh mesh, BuildMesh(c, v));
  if (absl::Status s = core::CheckVolumeStructure(mesh, core::kNoVolumeLimits); !s.ok()) {
    return c.Error(std::string(s.message()));
  }
  return mesh;
}

absl::StatusOr<VectorGrid> ParseVtkVectorGrid(std::string_view bytes, std::string_view name) {
  VtkCursor c(bytes, name);
  VtkContent v;
  v.keep_vectors = true;
  v.max_points = kMaxVectorGridNodes;
  LSQSURF_ASSIGN_OR_RETURN(const bool version5, ReadHeader(c, v));
  if (v.dataset != "STRUCTURED_POINTS") {
    return c.Error(core::StrCat("a velocity grid is DATASET STRUCTURED_POINTS (a regular grid), not ", v.dataset));
  }
  LSQSURF_RETURN_IF_ERROR(ReadSections(c, v, version5));
  // The product is bounded factor by factor: three large dimensions overflow even 64 bits.
  int64_t nodes = 1;
  for (int a = 0; a < 3; ++a) {
    if (v.dimensions[a] < 1) return c.Error("DIMENSIONS must be given and positive");
    nodes *= v.dimensions[a];
    if (nodes > kMaxVectorGridNodes) {
      return c.Error(core::StrCat("the grid has more than ", kMaxVectorGridNodes, " nodes (DIMENSIONS ",
                                  v.dimensions[0], " ", v.dimensions[1], " ", v.dimensions[2],
                                  "); at most that many are accepted"));
    }
  }
  if (v.point_count != nodes) return c.Error(core::StrCat("POINT_DATA must equal nx·ny·nz = ", nodes));
  if (!v.origin.allFinite() || !v.spacing.allFinite() || !(v.spacing.minCoeff() > 0)) {
    return c.Error("ORIGIN must be finite and SPACING positive");
  }
  if (v.vectors.empty()) return c.Error("the point data holds no VECTORS array");
  VectorGrid grid;
  for (int a = 0; a < 3; ++a) grid.dims[a] = static_cast<int>(v.dimensions[a]);
  grid.origin = v.origin;
  grid.spacing = v.spacing;
  grid.values.resize(static_cast<size_t>(nodes));
  for (size_t i = 0; i < grid.values.size(); ++i) {
    grid.values[i] = Vec3d(v.vectors[3 * i], v.vectors[3 * i + 1], v.vectors[3 * i + 2]);
    if (!grid.values[i].allFinite()) return c.Error(core::StrCat("vector ", i, " is not finite"));
  }
  return grid;
}

namespace {

template <class T>
void AppendBigEndian(std::string& out, T value) {
  char bytes[sizeof(T)];
  std::memcpy(bytes, &value, sizeof(T));
  if constexpr (std::endian::native == std::endian::little) std::reverse(bytes, bytes + sizeof(T));
  out.append(bytes, sizeof(T));
}

// One number per line (ASCII) or big-endian binary followed by a newline.
template <class T>
void AppendValues(std::string& out, std::span<const T> values, bool binary) {
  for (T x : values) {
    if (binary) {
      AppendBigEndian(out, x);
    } else {
      core::StrAppend(&out, x, "\n");
    }
  }
  if (binary) out += '\n';
}

}  // namespace

std::string EncodeLegacyVtk(const VolumeMesh& mesh, bool binary) {
  std::string out = core::StrCat("# vtk DataFile Version 4.2\nlsqsurf volume\n", binary ? "BINARY" : "ASCII",
                                 "\nDATASET UNSTRUCTURED_GRID\nPOINTS ", mesh.vertex_count(), " float\n");
  std::vector<float> coords;
  coords.reserve(mesh.vertex_count() * 3);
  for (const Vec3f& p : mesh.positions) coords.insert(coords.end(), {p.x(), p.y(), p.z()});
  AppendValues<float>(out, coords, binary);
  std::vector<int32_t> cells;
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    const auto v = mesh.cell(c);
    cells.push_back(static_cast<int32_t>(v.size()));
    for (uint32_t i : v) cells.push_back(static_cast<int32_t>(i));
  }
  core::StrAppend(&out, "CELLS ", mesh.cell_count(), " ", cells.size(), "\n");
  AppendValues<int32_t>(out, cells, binary);
  core::StrAppend(&out, "CELL_TYPES ", mesh.cell_count(), "\n");
  std::vector<int32_t> types(mesh.cell_types.begin(), mesh.cell_types.end());
  AppendValues<int32_t>(out, types, binary);
  if (!mesh.fields.empty()) core::StrAppend(&out, "POINT_DATA ", mesh.vertex_count(), "\n");
  for (const VertexField& f : mesh.fields) {
    if (f.components == 3) {
      core::StrAppend(&out, "VECTORS ", f.name, " float\n");
    } else {
      core::StrAppend(&out, "SCALARS ", f.name, " float ", f.components, "\nLOOKUP_TABLE default\n");
    }
    AppendValues<float>(out, f.values, binary);
  }
  return out;
}

std::string EncodeVtkVectorGrid(const VectorGrid& grid, bool binary) {
  std::string out = core::StrCat("# vtk DataFile Version 3.0\nvelocity\n", binary ? "BINARY" : "ASCII",
                                 "\nDATASET STRUCTURED_POINTS\nDIMENSIONS ", grid.dims[0], " ", grid.dims[1], " ",
                                 grid.dims[2], "\n");
  for (const auto& [key, v] : {std::pair{"ORIGIN", grid.origin}, std::pair{"SPACING", grid.spacing}}) {
    char line[128];
    std::snprintf(line, sizeof(line), "%s %.17g %.17g %.17g\n", key, v.x(), v.y(), v.z());
    out += line;
  }
  core::StrAppend(&out, "POINT_DATA ", grid.values.size(), "\nVECTORS velocity float\n");
  std::vector<float> values;
  values.reserve(grid.values.size() * 3);
  for (const Vec3d& v : grid.values) values.insert(values.end(), {float(v.x()), float(v.y()), float(v.z())});
  AppendValues<float>(out, values, binary);
  return out;
}

}  // namespace lsqsurf::io
