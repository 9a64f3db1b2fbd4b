#include "worker/io/vtk_grid.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "worker/core/strings.h"
#include "worker/io/text_scan.h"

namespace lsqsurf::io {
namespace {

using internal::LineReader;
using internal::NextToken;
using internal::ParseNumber;

bool IsSpace(char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r'; }

// Copies sizeof(T) bytes between big-endian storage and a native T (the same in both ways).
template <typename T>
void SwapCopy(const char* from, char* to) {
  std::memcpy(to, from, sizeof(T));
  if constexpr (std::endian::native == std::endian::little) std::reverse(to, to + sizeof(T));
}

// Reads `count` big-endian IEEE values of type T from `data`.
template <typename T>
void ReadBigEndian(std::string_view data, size_t count, std::vector<double>& out) {
  out.resize(count);
  for (size_t i = 0; i < count; ++i) {
    T value;
    SwapCopy<T>(data.data() + i * sizeof(T), reinterpret_cast<char*>(&value));
    out[i] = static_cast<double>(value);
  }
}

}  // namespace

absl::StatusOr<VectorGrid> ParseVtkVectorGrid(std::string_view bytes, std::string_view name) {
  auto error = [&](size_t line, std::string_view what) {
    return absl::InvalidArgumentError(core::StrCat(name, ": line ", line, ": ", what));
  };
  LineReader lines(bytes);
  std::string_view line;
  if (!lines.Next(line) || !line.starts_with("# vtk DataFile Version")) {
    return error(1, "not a legacy VTK file (expected '# vtk DataFile Version ...')");
  }
  if (!lines.Next(line)) return error(2, "the file ends after its first line");
  if (!lines.Next(line)) return error(3, "the file ends before ASCII or BINARY");
  std::string_view mode = line;
  const std::string_view mode_token = NextToken(mode);
  if (mode_token != "ASCII" && mode_token != "BINARY") return error(3, "expected ASCII or BINARY");
  const bool binary = mode_token == "BINARY";

  VectorGrid grid;
  bool have_dims = false, have_dataset = false;
  int64_t point_data = -1;
  bool doubles = false;
  // Header keywords up to the VECTORS line.
  for (;;) {
    if (!lines.Next(line)) return error(lines.line_number(), "the file ends before its VECTORS data");
    std::string_view rest = line;
    const std::string_view key = NextToken(rest);
    const size_t at = lines.line_number();
    if (key.empty()) continue;
    auto three = [&](auto& target, const char* what) -> absl::Status {
      for (int a = 0; a < 3; ++a) {
        if (!ParseNumber(NextToken(rest), target[a])) return error(at, core::StrCat(what, " needs three numbers"));
      }
      return absl::OkStatus();
    };
    if (key == "DATASET") {
      if (NextToken(rest) != "STRUCTURED_POINTS") {
        return error(at, "only DATASET STRUCTURED_POINTS (a regular grid) is supported");
      }
      have_dataset = true;
    } else if (key == "DIMENSIONS") {
      if (absl::Status s = three(grid.dims, "DIMENSIONS"); !s.ok()) return s;
      have_dims = true;
    } else if (key == "ORIGIN") {
      if (absl::Status s = three(grid.origin, "ORIGIN"); !s.ok()) return s;
    } else if (key == "SPACING" || key == "ASPECT_RATIO") {
      if (absl::Status s = three(grid.spacing, "SPACING"); !s.ok()) return s;
    } else if (key == "POINT_DATA") {
      if (!ParseNumber(NextToken(rest), point_data)) return error(at, "POINT_DATA needs a count");
    } else if (key == "VECTORS") {
      NextToken(rest);  // The array's name.
      const std::string_view type = NextToken(rest);
      if (type != "float" && type != "double") return error(at, "VECTORS must be float or double");
      doubles = type == "double";
      break;
    } else {
      return error(at, core::StrCat("unexpected '", key,
                                    "'; expected DATASET, DIMENSIONS, ORIGIN, SPACING, POINT_DATA or VECTORS"));
    }
  }
  const size_t vectors_line = lines.line_number();
  if (!have_dataset || !have_dims)
    return error(vectors_line, "DATASET STRUCTURED_POINTS and DIMENSIONS must come before VECTORS");
  // The product is bounded factor by factor: three large dimensions overflow even 64 bits
  // (undefined behaviour, found by fuzzing).
  int64_t nodes = 1;
  for (int a = 0; a < 3; ++a) {
    if (grid.dims[a] < 1) return error(vectors_line, "DIMENSIONS must be positive");
    nodes *= grid.dims[a];
    if (nodes > kMaxVectorGridNodes) {
      return error(vectors_line,
                   core::StrCat("the grid has more than ", kMaxVectorGridNodes, " nodes (DIMENSIONS ", grid.dims[0],
                                " ", grid.dims[1], " ", grid.dims[2], "); at most that many are accepted"));
    }
  }
  if (point_data != nodes) return error(vectors_line, core::StrCat("POINT_DATA must equal nx·ny·nz = ", nodes));
  if (!grid.origin.allFinite() || !grid.spacing.allFinite() || !(grid.spacing.minCoeff() > 0)) {
    return error(vectors_line, "ORIGIN must be finite and SPACING positive");
  }

  const auto count = static_cast<size_t>(nodes) * 3;
  std::string_view data = bytes.substr(lines.offset() <= bytes.size() ? lines.offset() : bytes.size());
  std::vector<double> flat;
  if (binary) {
    const size_t size = doubles ? sizeof(double) : sizeof(float);
    if (data.size() < count * size) {
      return error(vectors_line, core::StrCat("the binary VECTORS data is truncated: ", data.size(),
                                              " bytes, expected ", count * size));
    }
    if (doubles) {
      ReadBigEndian<double>(data, count, flat);
    } else {
      ReadBigEndian<float>(data, count, flat);
    }
  } else {
    flat.reserve(count);
    size_t pos = 0;
    while (flat.size() < count) {
      while (pos < data.size() && IsSpace(data[pos])) ++pos;
      if (pos >= data.size()) {
        return error(vectors_line,
                     core::StrCat("the VECTORS data is truncated: ", flat.size(), " of ", count, " values"));
      }
      size_t end = pos;
      while (end < data.size() && !IsSpace(data[end])) ++end;
      double v = 0;
      if (!ParseNumber(data.substr(pos, end - pos), v)) {
        return error(vectors_line, core::StrCat("value ", flat.size(), " of VECTORS is not a number"));
      }
      flat.push_back(v);
      pos = end;
    }
  }
  grid.values.resize(static_cast<size_t>(nodes));
  for (size_t i = 0; i < grid.values.size(); ++i) {
    grid.values[i] = core::Vec3d(flat[3 * i], flat[3 * i + 1], flat[3 * i + 2]);
    if (!grid.values[i].allFinite()) {
      return absl::InvalidArgumentError(core::StrCat(name, ": vector ", i, " is not finite"));
    }
  }
  return grid;
}

std::string EncodeVtkVectorGrid(const VectorGrid& grid, bool binary) {
  std::string out = "# vtk DataFile Version 3.0\nvelocity\n";
  out += binary ? "BINARY\n" : "ASCII\n";
  out += "DATASET STRUCTURED_POINTS\n";
  out += core::StrCat("DIMENSIONS ", grid.dims[0], " ", grid.dims[1], " ", grid.dims[2], "\n");
  auto append_doubles = [&](const char* key, const core::Vec3d& v) {
    char buf[128];
    std::snprintf(buf, sizeof(buf), "%s %.17g %.17g %.17g\n", key, v.x(), v.y(), v.z());
    out += buf;
  };
  append_doubles("ORIGIN", grid.origin);
  append_doubles("SPACING", grid.spacing);
  out += core::StrCat("POINT_DATA ", grid.values.size(), "\nVECTORS velocity float\n");
  for (const core::Vec3d& v : grid.values) {
    if (binary) {
      for (int a = 0; a < 3; ++a) {
        const auto value = static_cast<float>(v[a]);
        char stored[sizeof(float)];
        SwapCopy<float>(reinterpret_cast<const char*>(&value), stored);
        out.append(stored, sizeof(stored));
      }
    } else {
      internal::AppendFloats(out, {static_cast<float>(v.x()), static_cast<float>(v.y()), static_cast<float>(v.z())});
    }
  }
  return out;
}

}  // namespace lsqsurf::io
