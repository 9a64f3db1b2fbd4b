#include "worker/io/obj_xyz.h"

#include <algorithm>
#include <cstdint>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/text_scan.h"

namespace lsqsurf::io {
namespace {

using internal::LineReader;
using internal::NextToken;
using internal::ParseNumber;

absl::Status LineError(std::string_view name, size_t line, std::string_view what) {
  return absl::InvalidArgumentError(core::StrCat(name, ": line ", line, ": ", what));
}

bool ReadVec3(std::string_view& rest, core::Vec3f& out) {
  for (int k = 0; k < 3; ++k) {
    float v = 0;
    if (!ParseNumber(NextToken(rest), v)) return false;
    out[k] = v;
  }
  return true;
}

}  // namespace

absl::StatusOr<core::TriangleMesh> ParseObj(std::string_view text, std::string_view name) {
  core::TriangleMesh mesh;
  std::vector<core::Vec3f> normals, colours;
  LineReader lines(text);
  std::string_view line;
  std::vector<uint32_t> polygon;
  while (lines.Next(line)) {
    std::string_view rest = line;
    const std::string_view key = NextToken(rest);
    if (key == "v") {
      core::Vec3f p, rgb;
      if (!ReadVec3(rest, p)) return LineError(name, lines.line_number(), "expected 'v x y z'");
      mesh.vertices.push_back(p);
      // A vertex colour, 0..1 ("v x y z r g b", as MeshLab writes it): kept when every vertex has one.
      if (ReadVec3(rest, rgb)) colours.push_back(rgb);
    } else if (key == "vn") {
      core::Vec3f n;
      if (!ReadVec3(rest, n)) return LineError(name, lines.line_number(), "expected 'vn x y z'");
      normals.push_back(n);
    } else if (key == "f") {
      polygon.clear();
      for (std::string_view tok = NextToken(rest); !tok.empty(); tok = NextToken(rest)) {
        const std::string_view first = tok.substr(0, tok.find('/'));
        int64_t idx = 0;
        if (!ParseNumber(first, idx) || idx == 0) {
          return LineError(name, lines.line_number(), core::StrCat("bad face index '", tok, "'"));
        }
        const auto n = static_cast<int64_t>(mesh.vertices.size());
        const int64_t resolved = idx > 0 ? idx - 1 : n + idx;
        if (resolved < 0 || resolved >= n) {
          return LineError(name, lines.line_number(),
                           core::StrCat("face index ", idx, " is outside the ", n, " vertices defined so far"));
        }
        polygon.push_back(static_cast<uint32_t>(resolved));
      }
      if (polygon.size() < 3) return LineError(name, lines.line_number(), "face with fewer than 3 vertices");
      for (size_t j = 1; j + 1 < polygon.size(); ++j) mesh.faces.push_back({polygon[0], polygon[j], polygon[j + 1]});
    }
  }
  if (mesh.vertices.empty()) return absl::InvalidArgumentError(core::StrCat(name, ": OBJ file has no vertices"));
  if (normals.size() == mesh.vertices.size()) mesh.normals = std::move(normals);
  if (!colours.empty() && colours.size() == mesh.vertices.size()) {
    for (int c = 0; c < 3; ++c) {
      core::ScalarAttribute channel{core::kColourChannels[static_cast<size_t>(c)], std::vector<float>(colours.size())};
      for (size_t v = 0; v < colours.size(); ++v) channel.values[v] = 255 * colours[v][c];
      mesh.vertex_attributes.push_back(std::move(channel));
    }
  }
  return mesh;
}

std::string EncodeObj(const core::TriangleMesh& mesh) {
  std::string out = "# written by lsqsurf\n";
  const bool normals = mesh.normals.size() == mesh.vertices.size() && !mesh.vertices.empty();
  const auto channel = core::ColourChannels(mesh.vertex_attributes, mesh.vertices.size());
  const bool colour = channel[0] != nullptr;
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    const auto& v = mesh.vertices[i];
    out += "v ";
    if (colour) {  // Vertex colours 0..1 after the position, as MeshLab and Open3D read them.
      auto unit = [&](size_t c) { return std::clamp(channel[c]->values[i] / 255.0f, 0.0f, 1.0f); };
      internal::AppendFloats(out, {v.x(), v.y(), v.z(), unit(0), unit(1), unit(2)});
    } else {
      internal::AppendFloats(out, {v.x(), v.y(), v.z()});
    }
  }
  if (normals) {
    for (const auto& n : mesh.normals) {
      out += "vn ";
      internal::AppendFloats(out, {n.x(), n.y(), n.z()});
    }
  }
  for (const auto& f : mesh.faces) {
    if (normals) {
      core::StrAppend(&out, "f ", f[0] + 1, "//", f[0] + 1, " ", f[1] + 1, "//", f[1] + 1, " ", f[2] + 1, "//",
                      f[2] + 1, "\n");
    } else {
      core::StrAppend(&out, "f ", f[0] + 1, " ", f[1] + 1, " ", f[2] + 1, "\n");
    }
  }
  return out;
}

absl::StatusOr<core::PointCloud> ParseXyz(std::string_view text, std::string_view name) {
  core::PointCloud cloud;
  XyzReader reader(text, name);
  LSQSURF_RETURN_IF_ERROR(reader.Read(SIZE_MAX, cloud));
  return cloud;
}

absl::Status XyzReader::Read(size_t max_points, core::PointCloud& cloud) {
  std::string_view line;
  for (size_t read = 0; read < max_points && lines_.Next(line);) {
    line = line.substr(0, line.find('#'));
    std::string_view rest = line;
    double v[7];
    int n = 0;
    for (std::string_view tok = NextToken(rest); !tok.empty(); tok = NextToken(rest)) {
      if (n == 6) return LineError(name_, lines_.line_number(), "more than 6 values on a line");
      if (!ParseNumber(tok, v[n])) {
        return LineError(name_, lines_.line_number(), core::StrCat("'", tok, "' is not a number"));
      }
      ++n;
    }
    if (n == 0) continue;
    if (n != 3 && n != 6) {
      return LineError(name_, lines_.line_number(), core::StrCat("expected 3 or 6 values, found ", n));
    }
    if (columns_ == 0) columns_ = n;
    if (n != columns_) {
      return LineError(name_, lines_.line_number(),
                       core::StrCat("expected ", columns_, " values like the lines before, found ", n));
    }
    cloud.positions.emplace_back(static_cast<float>(v[0]), static_cast<float>(v[1]), static_cast<float>(v[2]));
    if (n == 6)
      cloud.normals.emplace_back(static_cast<float>(v[3]), static_cast<float>(v[4]), static_cast<float>(v[5]));
    ++read;
  }
  if (columns_ == 0) return absl::InvalidArgumentError(core::StrCat(name_, ": no points in XYZ file"));
  return absl::OkStatus();
}

std::string EncodeXyz(const core::PointCloud& cloud) {
  std::string out;
  for (size_t i = 0; i < cloud.size(); ++i) {
    const auto& p = cloud.positions[i];
    if (cloud.has_normals()) {
      const auto& n = cloud.normals[i];
      internal::AppendFloats(out, {p.x(), p.y(), p.z(), n.x(), n.y(), n.z()});
    } else {
      internal::AppendFloats(out, {p.x(), p.y(), p.z()});
    }
  }
  return out;
}

}  // namespace lsqsurf::io
