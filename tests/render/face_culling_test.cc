#include "worker/render/face_culling.h"

#include <gtest/gtest.h>

#include <utility>

#include "worker/core/mesh_metrics.h"
#include "worker/core/sphere_mesh.h"

namespace lsqsurf::render {
namespace {

OutsideWinding Winding(const core::TriangleMesh& m) { return ClosedMeshOutsideWinding(m.vertices, m.normals, m.faces); }

void FlipFaces(core::TriangleMesh& m, size_t first, size_t last) {
  for (size_t f = first; f < last; ++f) std::swap(m.faces[f][1], m.faces[f][2]);
}

// Two spheres side by side in one mesh.
core::TriangleMesh TwoSpheres() {
  core::TriangleMesh a = core::SphereMesh(12, 24), b = core::SphereMesh(12, 24);
  const auto offset = static_cast<uint32_t>(a.vertices.size());
  for (const core::Vec3f& v : b.vertices) a.vertices.push_back(v + core::Vec3f(3, 0, 0));
  a.normals.insert(a.normals.end(), b.normals.begin(), b.normals.end());
  for (core::Triangle f : b.faces) a.faces.push_back({f[0] + offset, f[1] + offset, f[2] + offset});
  return a;
}

TEST(FaceCulling, TheTestSphereIsClosedAndWoundOutwards) {
  // Independent truth: the sorting topology analysis and the divergence-theorem volume.
  const core::TriangleMesh sphere = core::SphereMesh(24, 48);
  const core::MeshTopology topology = core::AnalyzeTopology(sphere);
  EXPECT_TRUE(topology.watertight());
  EXPECT_TRUE(topology.consistently_oriented());
  EXPECT_EQ(topology.euler_characteristic(), 2);
  EXPECT_NEAR(core::EnclosedVolume(sphere), 4.18879, 0.05);
  EXPECT_EQ(Winding(sphere), OutsideWinding::kCounterClockwise);
}

TEST(FaceCulling, ReversedWindingIsClockwise) {
  core::TriangleMesh sphere = core::SphereMesh(24, 48);
  FlipFaces(sphere, 0, sphere.faces.size());
  EXPECT_EQ(Winding(sphere), OutsideWinding::kClockwise);
  sphere.normals.clear();  // The volume's sign alone.
  EXPECT_EQ(Winding(sphere), OutsideWinding::kClockwise);
}

TEST(FaceCulling, OpenOrInconsistentMeshesCullNothing) {
  core::TriangleMesh holed = core::SphereMesh(24, 48);
  holed.faces.erase(holed.faces.begin() + 100);
  EXPECT_EQ(Winding(holed), OutsideWinding::kUnknown);

  core::TriangleMesh one_flipped = core::SphereMesh(24, 48);
  FlipFaces(one_flipped, 100, 101);
  EXPECT_EQ(Winding(one_flipped), OutsideWinding::kUnknown);

  // Each sphere is closed and consistent, but they disagree: the normals catch it.
  core::TriangleMesh pair = TwoSpheres();
  EXPECT_EQ(Winding(pair), OutsideWinding::kCounterClockwise);
  FlipFaces(pair, pair.faces.size() / 2, pair.faces.size());
  EXPECT_EQ(Winding(pair), OutsideWinding::kUnknown);

  // Normals pointing inwards contradict the volume: not trusted.
  core::TriangleMesh inward = core::SphereMesh(24, 48);
  for (core::Vec3f& n : inward.normals) n = -n;
  EXPECT_EQ(Winding(inward), OutsideWinding::kUnknown);

  EXPECT_EQ(Winding(core::TriangleMesh{}), OutsideWinding::kUnknown);
}

}  // namespace
}  // namespace lsqsurf::render
