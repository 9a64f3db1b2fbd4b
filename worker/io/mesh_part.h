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

}  // namespace lsqsurf::io
