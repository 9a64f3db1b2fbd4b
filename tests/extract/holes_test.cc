// Closing small holes: slits and single faces cut from a closed sphere close again with the
// sphere's topology and nearly its volume; long borders and holes that touch at a vertex stay.
#include "worker/extract/holes.h"

#include <gtest/gtest.h>

#include <functional>
#include <numbers>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::extract::internal {
namespace {

using core::AnalyzeTopology;
using core::MeshTopology;
using core::TriangleMesh;

// A closed unit sphere marched on a grid from its exact distance field.
TriangleMesh Sphere() {
  const testing::SphereField field(1.0);
  core::LocalJobContext ctx;
  IsosurfaceParams p;
  p.cell_size = 0.1;
  auto r = ExtractIsosurface(field, testing::SphereCloud(2000).positions, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? r->mesh : TriangleMesh{};
}

// The mesh without the faces whose centroid `cut` picks.
TriangleMesh Without(TriangleMesh mesh, const std::function<bool(const core::Vec3f&)>& cut) {
  std::erase_if(mesh.faces, [&](const core::Triangle& f) {
    return cut((mesh.vertices[f[0]] + mesh.vertices[f[1]] + mesh.vertices[f[2]]) / 3.0f);
  });
  return mesh;
}

TEST(FillSmallHoles, ASlitAndACapCloseWithTheSpheresTopology) {
  const TriangleMesh sphere = Sphere();
  ASSERT_TRUE(AnalyzeTopology(sphere).watertight());
  TriangleMesh cut = Without(sphere, [](const core::Vec3f& c) {
    const bool slit = c.x() > 0.9f && std::abs(c.z()) < 0.05f && std::abs(c.y()) < 0.25f;
    const bool cap = c.z() > 0.985f;
    return slit || cap;
  });
  const MeshTopology before = AnalyzeTopology(cut);
  ASSERT_EQ(before.boundary_loops, 2);
  const size_t removed = sphere.faces.size() - cut.faces.size();
  ASSERT_GE(removed, 6u);

  EXPECT_EQ(FillSmallHoles(cut, 32), 2);
  const MeshTopology after = AnalyzeTopology(cut);
  EXPECT_TRUE(after.watertight());
  EXPECT_TRUE(after.consistently_oriented());
  EXPECT_EQ(after.euler_characteristic(), 2);
  EXPECT_EQ(after.non_manifold_edges, 0);
  // No vertex is added: the fill spans the border with two triangles fewer than it has edges.
  EXPECT_EQ(cut.vertices.size(), sphere.vertices.size());
  // Flat patches over small holes of a unit sphere lose little volume.
  EXPECT_NEAR(core::EnclosedVolume(cut) / core::EnclosedVolume(sphere), 1.0, 2e-3);
}

TEST(FillSmallHoles, LongBordersStayOpen) {
  TriangleMesh cut = Without(Sphere(), [](const core::Vec3f& c) { return c.z() > 0.5f; });
  const size_t faces = cut.faces.size();
  EXPECT_EQ(FillSmallHoles(cut, 32), 0);  // The border has about 2π · 0.87 / 0.07 edges.
  EXPECT_EQ(cut.faces.size(), faces);
}

TEST(FillSmallHoles, OneMissingFaceComesBackButTwoThatTouchAtAVertexDoNot) {
  const TriangleMesh sphere = Sphere();
  // Two faces around one vertex that share no edge with each other.
  const uint32_t v = sphere.faces[0][0];
  std::vector<size_t> around;
  for (size_t f = 0; f < sphere.faces.size(); ++f) {
    if (std::ranges::find(sphere.faces[f], v) != sphere.faces[f].end()) around.push_back(f);
  }
  ASSERT_GE(around.size(), 4u);
  auto share_edge = [&](size_t a, size_t b) {
    int common = 0;
    for (uint32_t x : sphere.faces[a]) common += std::ranges::find(sphere.faces[b], x) != sphere.faces[b].end();
    return common == 2;
  };
  size_t second = 0;
  for (size_t f : around) {
    if (f != around[0] && !share_edge(around[0], f)) second = f;
  }
  ASSERT_NE(second, 0u);

  TriangleMesh one = sphere;
  one.faces.erase(one.faces.begin() + static_cast<std::ptrdiff_t>(around[0]));
  EXPECT_EQ(FillSmallHoles(one, 32), 1);
  EXPECT_TRUE(AnalyzeTopology(one).watertight());

  TriangleMesh two = sphere;
  two.faces.erase(two.faces.begin() + static_cast<std::ptrdiff_t>(std::max(around[0], second)));
  two.faces.erase(two.faces.begin() + static_cast<std::ptrdiff_t>(std::min(around[0], second)));
  EXPECT_EQ(FillSmallHoles(two, 32), 0);  // Which way each border runs at v is ambiguous.
  EXPECT_EQ(AnalyzeTopology(two).boundary_edges, 6);
}

TEST(FillSmallHoles, ALoneTriangleIsNotDoubled) {
  TriangleMesh lone;
  lone.vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  lone.faces = {{0, 1, 2}};
  EXPECT_EQ(FillSmallHoles(lone, 32), 0);
  EXPECT_EQ(lone.faces.size(), 1u);
}

}  // namespace
}  // namespace lsqsurf::extract::internal
