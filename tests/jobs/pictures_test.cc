#include "worker/jobs/pictures.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <map>

#include "worker/core/sphere_mesh.h"
#include "worker/io/mesh_part.h"

namespace lsqsurf::jobs {
namespace {

using Corners = std::array<std::array<float, 3>, 3>;

// The mesh's triangles by the positions of their corners, rotated to start at the smallest, so
// that two meshes numbering their vertices differently compare equal.
std::multiset<Corners> TrianglesOf(const core::TriangleMesh& mesh) {
  std::multiset<Corners> out;
  for (const core::Triangle& f : mesh.faces) {
    Corners c;
    for (int k = 0; k < 3; ++k) {
      const core::Vec3f& p = mesh.vertices[f[k]];
      c[k] = {p.x(), p.y(), p.z()};
    }
    std::rotate(c.begin(), std::min_element(c.begin(), c.end()), c.end());
    out.insert(c);
  }
  return out;
}

// The mesh in `parts` LQM parts, as the tiled engine writes them: the faces in runs, each part
// bringing the vertices no earlier part had, its faces naming earlier parts' vertices too. A
// "height" attribute rides along.
std::vector<std::string> InParts(const core::TriangleMesh& mesh, size_t parts) {
  std::vector<int64_t> number(mesh.vertices.size(), -1);
  int64_t next = 0;
  std::vector<std::string> out;
  const size_t per_part = (mesh.faces.size() + parts - 1) / parts;
  for (size_t begin = 0; begin < mesh.faces.size(); begin += per_part) {
    const int64_t first = next;
    std::vector<core::Vec3f> vertices, normals;
    core::ScalarAttribute height{"height", {}};
    std::vector<std::array<int64_t, 3>> faces;
    for (size_t f = begin; f < std::min(mesh.faces.size(), begin + per_part); ++f) {
      std::array<int64_t, 3> face;
      for (int k = 0; k < 3; ++k) {
        const uint32_t v = mesh.faces[f][k];
        if (number[v] < 0) {
          number[v] = next++;
          vertices.push_back(mesh.vertices[v]);
          normals.push_back(mesh.normals[v]);
          height.values.push_back(mesh.vertices[v].z());
        }
        face[k] = number[v];
      }
      faces.push_back(face);
    }
    const std::vector<core::ScalarAttribute> attributes = {height};
    out.push_back(io::EncodeMeshPart(first, vertices, normals, attributes, faces));
  }
  return out;
}

TEST(MeshPartPieces, ThePiecesHoldEveryTriangleOnceWithItsOwnCorners) {
  const core::TriangleMesh sphere = core::SphereMesh(24, 48);
  const std::vector<std::string> parts = InParts(sphere, 5);
  ASSERT_EQ(parts.size(), 5u);
  const MeshPartPieces pieces(
      static_cast<int64_t>(parts.size()), [&](int64_t p) { return parts[static_cast<size_t>(p)]; }, "height");
  core::TriangleMesh joined;
  int visited = 0, borrowing = 0;
  ASSERT_TRUE(pieces
                  .ForEach([&](const core::TriangleMesh& piece) {
                    ++visited;
                    EXPECT_EQ(piece.normals.size(), piece.vertices.size());
                    EXPECT_EQ(piece.vertex_attributes.size(), 1u);
                    for (size_t v = 0; v < piece.vertices.size(); ++v) {
                      // Each vertex, its own or borrowed, keeps its normal and attribute.
                      EXPECT_NEAR(piece.normals[v].norm(), 1, 1e-5);
                      EXPECT_EQ(piece.vertex_attributes[0].values[v], piece.vertices[v].z());
                    }
                    const auto offset = static_cast<uint32_t>(joined.vertices.size());
                    joined.vertices.insert(joined.vertices.end(), piece.vertices.begin(), piece.vertices.end());
                    for (const core::Triangle& f : piece.faces) {
                      for (uint32_t v : f) EXPECT_LT(v, piece.vertices.size());
                      joined.faces.push_back({f[0] + offset, f[1] + offset, f[2] + offset});
                    }
                    // Later parts name vertices of earlier ones (the sphere's runs of faces touch).
                    const auto own = io::DecodeMeshPart(parts[static_cast<size_t>(visited - 1)])->vertices.size();
                    borrowing += piece.vertices.size() > own;
                    return absl::OkStatus();
                  })
                  .ok());
  EXPECT_EQ(visited, 5);
  EXPECT_EQ(borrowing, 4);
  EXPECT_EQ(TrianglesOf(joined), TrianglesOf(sphere));
}

TEST(MeshPartPieces, APartOutOfStepOrUnreadableIsNamed) {
  const core::TriangleMesh sphere = core::SphereMesh(12, 24);
  std::vector<std::string> parts = InParts(sphere, 3);
  const auto visit = [](const core::TriangleMesh&) { return absl::OkStatus(); };
  // Part 2 read in place of part 1: it starts past the vertices read so far.
  std::vector<std::string> skipped = {parts[0], parts[2]};
  const MeshPartPieces out_of_step(
      2, [&](int64_t p) { return skipped[static_cast<size_t>(p)]; }, "");
  const absl::Status step = out_of_step.ForEach(visit);
  EXPECT_EQ(step.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(step.message().find("mesh part 1 starts at vertex"), std::string::npos) << step;
  parts[1].resize(parts[1].size() / 2);
  const MeshPartPieces truncated(
      3, [&](int64_t p) { return parts[static_cast<size_t>(p)]; }, "");
  const absl::Status cut = truncated.ForEach(visit);
  EXPECT_EQ(cut.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(cut.message().find("mesh part 1: "), 0u) << cut;
  EXPECT_EQ(cut.message().find("mesh part:"), std::string::npos) << "named twice: " << cut;
  const MeshPartPieces missing(
      3, [](int64_t) -> absl::StatusOr<std::string> { return absl::NotFoundError("gone"); }, "");
  EXPECT_EQ(missing.ForEach(visit).code(), absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace lsqsurf::jobs
