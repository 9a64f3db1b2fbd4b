// Closing every hole on request: a marched sphere with caps and a bent region cut away closes
// again as one closed, consistently oriented sphere, the new vertices near the sphere (the thin
// plate follows its curvature), the enclosed volume near the sphere's, the new triangles about as
// long as the border's edges and few slivers; an open tube closes at both ends with the volume of
// a capped cylinder's order; a surface without holes is left as it is.
#include "worker/extract/hole_filling.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <numbers>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::extract {
namespace {

using core::AnalyzeTopology;
using core::MeshTopology;
using core::TriangleMesh;
using core::Vec3f;

TriangleMesh Sphere(double cell) {
  const testing::SphereField field(1.0);
  core::LocalJobContext ctx;
  IsosurfaceParams p;
  p.cell_size = cell;
  auto r = ExtractIsosurface(field, testing::SphereCloud(2000).positions, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? r->mesh : TriangleMesh{};
}

TriangleMesh Without(TriangleMesh mesh, const std::function<bool(const Vec3f&)>& cut) {
  std::erase_if(mesh.faces, [&](const core::Triangle& f) {
    return cut((mesh.vertices[f[0]] + mesh.vertices[f[1]] + mesh.vertices[f[2]]) / 3.0f);
  });
  return mesh;
}

double LongestEdge(const TriangleMesh& mesh, size_t first_face) {
  double longest = 0;
  for (size_t f = first_face; f < mesh.faces.size(); ++f) {
    for (size_t s = 0; s < 3; ++s) {
      const Vec3f d = mesh.vertices[mesh.faces[f][s]] - mesh.vertices[mesh.faces[f][(s + 1) % 3]];
      longest = std::max(longest, static_cast<double>(d.norm()));
    }
  }
  return longest;
}

double MedianEdge(const TriangleMesh& mesh) {
  std::vector<float> lengths;
  for (const core::Triangle& t : mesh.faces) lengths.push_back((mesh.vertices[t[0]] - mesh.vertices[t[1]]).norm());
  std::ranges::nth_element(lengths, lengths.begin() + static_cast<std::ptrdiff_t>(lengths.size() / 2));
  return lengths[lengths.size() / 2];
}

TEST(FillHoles, CapsAndABentHoleCloseTheSphereAgain) {
  const TriangleMesh sphere = Sphere(0.05);
  ASSERT_TRUE(AnalyzeTopology(sphere).watertight());
  // A wide cap (its border far longer than one piece is triangulated at once), a small one, and a
  // region bent over the sphere (two overlapping discs: a border that is neither flat nor convex).
  TriangleMesh cut = Without(sphere, [](const Vec3f& c) {
    const bool north = c.z() > 0.7f;
    const bool south = c.z() < -0.95f;
    const bool bent = (c - Vec3f(0.7f, 0.7f, 0)).norm() < 0.45f || (c - Vec3f(0.7f, -0.7f, 0)).norm() < 0.45f ||
                      (c - Vec3f(1, 0, 0)).norm() < 0.4f;
    return north || south || bent;
  });
  ASSERT_EQ(AnalyzeTopology(cut).boundary_loops, 3);
  const size_t old_vertices = cut.vertices.size(), old_faces = cut.faces.size();

  core::LocalJobContext ctx;
  auto stats = FillHoles(cut, {}, ctx);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->holes_filled, 3);
  EXPECT_EQ(stats->holes_left, 0);
  EXPECT_EQ(stats->unfaired, 0);
  EXPECT_EQ(stats->umbrella_faired, 0);  // Cotangent weights hold on a sphere; umbrella ones sag.
  EXPECT_EQ(static_cast<size_t>(stats->vertices_added), cut.vertices.size() - old_vertices);
  EXPECT_GT(stats->vertices_added, 200);

  const MeshTopology after = AnalyzeTopology(core::WeldByPosition(cut));
  EXPECT_TRUE(after.watertight());
  EXPECT_TRUE(after.consistently_oriented());
  EXPECT_EQ(after.components, 1);
  EXPECT_EQ(after.euler_characteristic(), 2);
  EXPECT_EQ(after.degenerate_faces, 0);

  // The thin plate bends with the sphere: a flat patch over the north cap would lie 0.3 inside.
  // (Over a wider cap, z > 0.6, it overshoots to 1.07: a thin plate that leaves its border at
  // the border's slope rises above the sphere, about 1.13 for a graph over the flat disc.)
  for (size_t v = old_vertices; v < cut.vertices.size(); ++v) {
    EXPECT_NEAR(cut.vertices[v].norm(), 1.0, 0.06) << "vertex " << v;
  }
  EXPECT_NEAR(core::EnclosedVolume(cut), core::EnclosedVolume(sphere), 0.02 * core::EnclosedVolume(sphere));
  // The fairing stretches the flat patch into a dome, its longest edges most.
  EXPECT_LT(LongestEdge(cut, old_faces), 4 * MedianEdge(sphere));
  TriangleMesh patch;
  patch.vertices = cut.vertices;
  patch.faces.assign(cut.faces.begin() + static_cast<std::ptrdiff_t>(old_faces), cut.faces.end());
  EXPECT_GT(core::MeasureTriangleQuality(patch).min_angle_p1, 5.0);
}

TEST(FillHoles, AnOpenTubeClosesAtBothEnds) {
  // A cylinder of radius 1 and height 2, open at both ends, 64 segments round.
  TriangleMesh tube;
  constexpr int kSegments = 64, kRings = 21;
  for (int i = 0; i < kRings; ++i) {
    for (int j = 0; j < kSegments; ++j) {
      const double phi = 2 * std::numbers::pi * j / kSegments;
      tube.vertices.emplace_back(std::cos(phi), std::sin(phi), -1.0 + 2.0 * i / (kRings - 1));
    }
  }
  auto at = [](int i, int j) { return static_cast<uint32_t>(i * kSegments + (j % kSegments)); };
  for (int i = 0; i + 1 < kRings; ++i) {
    for (int j = 0; j < kSegments; ++j) {
      tube.faces.push_back({at(i, j), at(i, j + 1), at(i + 1, j)});
      tube.faces.push_back({at(i, j + 1), at(i + 1, j + 1), at(i + 1, j)});
    }
  }
  ASSERT_EQ(AnalyzeTopology(tube).boundary_loops, 2);
  core::LocalJobContext ctx;
  auto stats = FillHoles(tube, {.thin_plate = false}, ctx);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->holes_filled, 2);
  const MeshTopology after = AnalyzeTopology(tube);
  EXPECT_TRUE(after.watertight());
  EXPECT_TRUE(after.consistently_oriented());
  EXPECT_EQ(after.euler_characteristic(), 2);
  // Membranes span the ends flat: the volume of the capped cylinder (the polygon's area × 2).
  const double polygon = 0.5 * kSegments * std::sin(2 * std::numbers::pi / kSegments);
  EXPECT_NEAR(std::abs(core::EnclosedVolume(tube)), 2 * polygon, 0.01 * 2 * polygon);
}

TEST(FillHoles, AClosedSurfaceStaysAsItIs) {
  TriangleMesh sphere = Sphere(0.1);
  const size_t vertices = sphere.vertices.size(), faces = sphere.faces.size();
  core::LocalJobContext ctx;
  auto stats = FillHoles(sphere, {}, ctx);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->holes_filled, 0);
  EXPECT_EQ(sphere.vertices.size(), vertices);
  EXPECT_EQ(sphere.faces.size(), faces);
}

}  // namespace
}  // namespace lsqsurf::extract
