// worker/io/mesh_part.h — one part of a mesh delivered in parts ("LQM1", little-endian): the
// vertices new in the part, numbered on from the parts before it, and its faces in the whole
// mesh's numbers. The parts joined in order are the mesh, with no welding to do; a reader holds
// one part at a time.
//
// Layout (core/binary.h): "LQM1", int64 first_vertex, the positions (count, then x y z float32
// each), the normals (count 0 or the positions', then floats), the number of attributes and for
// each its name (count, then bytes) and values (count = positions, float32), the faces (count,
// then three int64 vertex numbers each).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

struct MeshPart {
  int64_t first_vertex = 0;  // The whole mesh's number of vertices[0].
  std::vector<core::Vec3f> vertices;
  std::vector<core::Vec3f> normals;  // Empty, or one per vertex.
  std::vector<core::ScalarAttribute> attributes;
  std::vector<std::array<int64_t, 3>> faces;  // Each number below first_vertex + vertices.size().
};

std::string EncodeMeshPart(int64_t first_vertex, std::span<const core::Vec3f> vertices,
                           std::span<const core::Vec3f> normals, std::span<const core::ScalarAttribute> attributes,
                           std::span<const std::array<int64_t, 3>> faces);

// Errors: kInvalidArgument naming what is wrong (not LQM1, truncated, counts that disagree, a
// face number out of range).
absl::StatusOr<MeshPart> DecodeMeshPart(std::string_view bytes);

// Makes each part of a mesh delivered in parts, read in order, a mesh of its own (a tile to
// draw or to store alone): the part's vertices first, then those of earlier parts its faces name.
// Holds the positions, normals and kept attributes of every vertex read so far, never the faces:
// 24 bytes a vertex and 4 per kept attribute, against the joined mesh's 48 and 4.
class SelfContainedParts {
 public:
  // `attributes`: the names of the per-vertex attributes to carry; nullopt: all of the first
  // part's.
  explicit SelfContainedParts(std::optional<std::vector<std::string>> attributes = std::nullopt)
      : wanted_(std::move(attributes)) {}
  // The next part as a mesh of its own. Errors: kInvalidArgument when the part does not follow on
  // from those before it (its first vertex), or disagrees with the first part on normals or a
  // carried attribute.
  absl::StatusOr<core::TriangleMesh> Next(const MeshPart& part);
  int64_t vertices() const { return static_cast<int64_t>(positions_.size()); }

 private:
  absl::Status Remember(const MeshPart& part);
  std::optional<std::vector<std::string>> wanted_;
  int64_t parts_ = 0;
  bool normals_ = false;
  std::vector<core::Vec3f> positions_, normals_seen_;
  std::vector<std::string> names_;                     // Carried attributes, in the first part's order.
  std::vector<std::vector<float>> values_;             // Per carried attribute, per vertex.
  std::vector<const core::ScalarAttribute*> in_part_;  // The current part's of each carried one.
};

}  // namespace lsqsurf::io
