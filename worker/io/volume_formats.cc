#include "worker/io/volume_formats.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <limits>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"
#include "worker/io/ply.h"

namespace lsqsurf::io {
namespace {

using core::Vec3d;
using core::VertexField;
using core::VolumeMesh;

std::vector<std::string> SplitOn(std::string_view s, char separator) {
  std::vector<std::string> out;
  size_t start = 0;
  for (size_t i = 0; i <= s.size(); ++i) {
    if (i == s.size() || s[i] == separator) {
      out.emplace_back(s.substr(start, i - start));
      start = i + 1;
    }
  }
  return out;
}

}  // namespace

absl::StatusOr<VolumeMesh> ParseRawVolume(std::string_view bytes, std::string_view layout,
                                          std::string_view field_name) {
  auto bad = [&](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("raw layout '", layout, "': ", why,
                                                   " (expected NXxNYxNZ:TYPE[:SPACING], e.g. 32x32x32:uint8:0.1)"));
  };
  const std::vector<std::string> parts = SplitOn(layout, ':');
  if (parts.size() < 2 || parts.size() > 3) return bad("wrong number of parts");
  const std::vector<std::string> dims = SplitOn(parts[0], 'x');
  if (dims.size() != 3) return bad("three dimensions are needed");
  std::array<int, 3> d{};
  for (int a = 0; a < 3; ++a) {
    auto [p, ec] = std::from_chars(dims[a].data(), dims[a].data() + dims[a].size(), d[a]);
    if (ec != std::errc() || p != dims[a].data() + dims[a].size() || d[a] < 1 || d[a] > 65536) {
      return bad(core::StrCat("dimension '", dims[a], "' is not a count within [1, 65536]"));
    }
  }
  static const std::array<std::pair<std::string_view, int>, 8> kTypes = {{{"uint8", 1},
                                                                          {"int8", 1},
                                                                          {"uint16", 2},
                                                                          {"int16", 2},
                                                                          {"uint32", 4},
                                                                          {"int32", 4},
                                                                          {"float32", 4},
                                                                          {"float64", 8}}};
  int size = 0;
  for (const auto& [type_name, type_size] : kTypes) {
    if (parts[1] == type_name) size = type_size;
  }
  if (size == 0) return bad(core::StrCat("unknown type '", parts[1], "'"));
  Vec3d spacing = Vec3d::Ones();
  if (parts.size() == 3) {
    const std::vector<std::string> s = SplitOn(parts[2], ',');
    if (s.size() != 1 && s.size() != 3) return bad("the spacing is one number or three separated by commas");
    for (int a = 0; a < 3; ++a) {
      const std::string& t = s[s.size() == 1 ? 0 : a];
      double value = 0;
      auto [p, ec] = std::from_chars(t.data(), t.data() + t.size(), value);
      if (ec != std::errc() || p != t.data() + t.size() || !(value > 0) || !std::isfinite(value)) {
        return bad(core::StrCat("spacing '", t, "' is not a positive number"));
      }
      spacing[a] = value;
    }
  }
  const uint64_t count = static_cast<uint64_t>(d[0]) * d[1] * d[2];
  if (bytes.size() != count * size) {
    return absl::InvalidArgumentError(core::StrCat("the raw volume has ", bytes.size(), " bytes; ", d[0], "x", d[1],
                                                   "x", d[2], " ", parts[1], " values need ", count * size));
  }
  VolumeMesh mesh;
  VertexField field{std::string(field_name), 1, std::vector<float>(count)};
  mesh.positions.reserve(count);
  for (int k = 0; k < d[2]; ++k) {
    for (int j = 0; j < d[1]; ++j) {
      for (int i = 0; i < d[0]; ++i) mesh.positions.push_back(Vec3d(i, j, k).cwiseProduct(spacing).cast<float>());
    }
  }
  for (uint64_t i = 0; i < count; ++i) {
    const char* p = bytes.data() + i * size;
    double value = 0;
    auto load = [&]<class T>(T) {
      T x;
      std::memcpy(&x, p, sizeof(T));
      value = static_cast<double>(x);
    };
    if (parts[1] == "uint8") load(uint8_t{});
    if (parts[1] == "int8") load(int8_t{});
    if (parts[1] == "uint16") load(uint16_t{});
    if (parts[1] == "int16") load(int16_t{});
    if (parts[1] == "uint32") load(uint32_t{});
    if (parts[1] == "int32") load(int32_t{});
    if (parts[1] == "float32") load(float{});
    if (parts[1] == "float64") load(double{});
    field.values[i] = static_cast<float>(value);
  }
  mesh.fields.push_back(std::move(field));
  core::AddStructuredHexahedra(mesh, d[0], d[1], d[2]);
  return mesh;
}

absl::StatusOr<VolumeMesh> ParsePlyVolume(std::string_view bytes, std::string_view name) {
  LSQSURF_ASSIGN_OR_RETURN(core::TriangleMesh ply, ParsePly(bytes, name));
  VolumeMesh mesh;
  mesh.positions = std::move(ply.vertices);
  for (core::ScalarAttribute& a : ply.vertex_attributes) mesh.fields.push_back({a.name, 1, std::move(a.values)});
  if (mesh.fields.empty()) {
    return absl::InvalidArgumentError(
        core::StrCat(name, ": the PLY vertices carry no values (add a scalar property besides x, y, z)"));
  }
  return mesh;
}

absl::StatusOr<VolumeMesh> ReadVolumeFile(const std::string& path) {
  LSQSURF_ASSIGN_OR_RETURN(std::string bytes, ReadFileBytes(path));
  std::string lower = path;
  std::transform(lower.begin(), lower.end(), lower.begin(), [](unsigned char ch) { return std::tolower(ch); });
  if (lower.ends_with(".vtk")) return ParseLegacyVtk(bytes, path);
  if (lower.ends_with(".ply")) return ParsePlyVolume(bytes, path);
  if (lower.ends_with(".vtu")) return ParseVtu(bytes, path);
  return absl::InvalidArgumentError(
      core::StrCat(path,
                   ": unknown volume format; use .vtk (legacy VTK), .vtu (VTK XML), .ply (points with values) or a raw "
                   "volume with --raw"));
}

}  // namespace lsqsurf::io
