// Mesh enhancement: corner snapping before marching, tangential relaxation and edge flips after it.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <set>
#include <utility>

#include "tests/polyhedra.h"
#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/j1a_isosurface.h"
#include "worker/extract/relax.h"

namespace lsqsurf::extract {
namespace {

using core::LocalJobContext;
using core::MeshTopology;

IsosurfaceResult Extract(const ImplicitFunction& f, const core::PointCloud& seeds, double cell,
                         const MarchingOptions& marching) {
  LocalJobContext ctx;
  J1aIsosurfaceParams p;
  p.cell_size = cell;
  p.marching = marching;
  auto r = ExtractIsosurfaceJ1a(f, seeds.positions, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? *std::move(r) : IsosurfaceResult{};
}

void ExpectClosed(const core::TriangleMesh& mesh, int euler) {
  const MeshTopology t = AnalyzeTopology(mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_TRUE(t.consistently_oriented());
  EXPECT_EQ(t.degenerate_faces, 0);
  EXPECT_EQ(t.euler_characteristic(), euler);
  EXPECT_TRUE(AnalyzeTopology(core::WeldByPosition(mesh)).watertight());
}

TEST(Enhancement, SnappedCornersKeepTheSurfaceClosedAndOnTheSphere) {
  const testing::SphereField sphere(1.0);
  MarchingOptions snap;
  snap.snap_share = 0.3;
  const IsosurfaceResult plain = Extract(sphere, testing::SphereCloud(2000), 0.08, {});
  const IsosurfaceResult snapped = Extract(sphere, testing::SphereCloud(2000), 0.08, snap);
  ExpectClosed(snapped.mesh, 2);
  EXPECT_GT(snapped.stats.snapped_corners, 100);
  for (const auto& v : snapped.mesh.vertices) ASSERT_NEAR(v.cast<double>().norm(), 1.0, 1e-5);
  const double exact = 4.0 / 3.0 * std::numbers::pi;
  EXPECT_NEAR(EnclosedVolume(snapped.mesh) / exact, 1.0, 0.01);
  const double before = MeasureTriangleQuality(plain.mesh).min_angle_p1;
  const double after = MeasureTriangleQuality(snapped.mesh).min_angle_p1;
  std::printf("sphere, snapped corners %lld: smallest-angle 1st percentile %.1f -> %.1f degrees\n",
              static_cast<long long>(snapped.stats.snapped_corners), before, after);
  EXPECT_GT(after, before + 2);
}

TEST(Enhancement, SnappingKeepsATorusATorus) {
  const testing::TorusField torus(1.0, 0.35);
  MarchingOptions snap;
  snap.snap_share = 0.3;
  const IsosurfaceResult r = Extract(torus, testing::TorusCloud(4000, 1.0, 0.35), 0.05, snap);
  ExpectClosed(r.mesh, 0);
  const double exact = 2 * std::numbers::pi * std::numbers::pi * 1.0 * 0.35 * 0.35;
  EXPECT_NEAR(EnclosedVolume(r.mesh) / exact, 1.0, 0.01);
}

TEST(Enhancement, RelaxationEvensOutTrianglesAndStaysOnTheSurface) {
  const testing::TorusField torus(1.0, 0.35);
  MarchingOptions relax;
  relax.relax_steps = 4;
  const IsosurfaceResult plain = Extract(torus, testing::TorusCloud(4000, 1.0, 0.35), 0.05, {});
  const IsosurfaceResult relaxed = Extract(torus, testing::TorusCloud(4000, 1.0, 0.35), 0.05, relax);
  ExpectClosed(relaxed.mesh, 0);
  EXPECT_EQ(relaxed.mesh.faces.size(), plain.mesh.faces.size());  // Only positions change.
  double worst = 0;
  for (const auto& v : relaxed.mesh.vertices) worst = std::max(worst, std::abs(torus.Value(v.cast<double>()).value));
  const core::TriangleQuality before = MeasureTriangleQuality(plain.mesh);
  const core::TriangleQuality after = MeasureTriangleQuality(relaxed.mesh);
  std::printf(
      "torus, %lld vertices relaxed: 1st percentile %.1f -> %.1f degrees, aspect p99 %.2f -> %.2f, |F| <= %.2g\n",
      static_cast<long long>(relaxed.stats.relaxed_vertices), before.min_angle_p1, after.min_angle_p1,
      before.aspect_ratio_p99, after.aspect_ratio_p99, worst);
  EXPECT_LT(worst, 1e-4);  // One Newton step after a move of a fraction of an edge.
  EXPECT_GT(after.min_angle_p1, before.min_angle_p1 + 5);
  EXPECT_LT(after.aspect_ratio_p99, before.aspect_ratio_p99);
}

TEST(Enhancement, RelaxationLeavesCreasesWhereTheyAre) {
  const testing::TurnedPolyhedron cube = testing::Cube();
  MarchingOptions sharp;
  sharp.crease_angle = 30;
  MarchingOptions both = sharp;
  both.relax_steps = 4;
  const core::PointCloud seeds = cube.Sample(3000);
  const IsosurfaceResult a = Extract(cube, seeds, 0.06, sharp);
  const IsosurfaceResult b = Extract(cube, seeds, 0.06, both);
  ExpectClosed(b.mesh, 2);
  const double edges_a = testing::EdgeDistance(a.mesh, cube, testing::CubeEdges());
  const double edges_b = testing::EdgeDistance(b.mesh, cube, testing::CubeEdges());
  std::printf("cube: edge distance %.3g with relaxation, %.3g without; volume %.6f\n", edges_b, edges_a,
              EnclosedVolume(b.mesh));
  EXPECT_LT(edges_b, 1.5 * edges_a + 1e-4);
  EXPECT_NEAR(EnclosedVolume(b.mesh), 1.0, 2e-4);
}

// Points of a lattice of unit rows `row_height` apart, each row shifted by half a unit; each
// rhombus of four split along its long diagonal, so every triangle has a smallest angle of
// atan(row_height / 1.5) (16° here, where the short diagonal gives atan(2 row_height), 41°). Rows
// above `fold_row` are turned up by 90° about that row's line: the mesh folds along lattice edges.
core::TriangleMesh BadlySplitLattice(int size, int fold_row, std::vector<uint64_t>& rhombus) {
  core::TriangleMesh mesh;
  const double h = std::sqrt(3.0) / 4;  // Row height.
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      const double x = i + 0.5 * j, y = h * j;
      const double fold_y = h * fold_row;
      mesh.vertices.push_back(
          y <= fold_y ? core::Vec3f(static_cast<float>(x), static_cast<float>(y), 0)
                      : core::Vec3f(static_cast<float>(x), static_cast<float>(fold_y), static_cast<float>(y - fold_y)));
    }
  }
  auto at = [&](int i, int j) { return static_cast<uint32_t>(j * size + i); };
  rhombus.clear();
  for (int j = 0; j + 1 < size; ++j) {
    for (int i = 0; i + 1 < size; ++i) {
      mesh.faces.push_back({at(i, j), at(i + 1, j), at(i + 1, j + 1)});
      mesh.faces.push_back({at(i, j), at(i + 1, j + 1), at(i, j + 1)});
      rhombus.push_back(static_cast<uint64_t>(j * size + i));
      rhombus.push_back(static_cast<uint64_t>(j * size + i));
    }
  }
  return mesh;
}

std::set<std::pair<uint32_t, uint32_t>> Edges(const core::TriangleMesh& mesh) {
  std::set<std::pair<uint32_t, uint32_t>> edges;
  for (const core::Triangle& t : mesh.faces) {
    for (size_t k = 0; k < 3; ++k) edges.insert(std::minmax(t[k], t[(k + 1) % 3]));
  }
  return edges;
}

TEST(Enhancement, FlipsTurnThinPairsIntoEquilateralOnesAndLeaveFoldsAlone) {
  const int size = 12, fold_row = 6;
  std::vector<uint64_t> cells;
  core::TriangleMesh mesh = BadlySplitLattice(size, fold_row, cells);
  const core::TriangleMesh before = mesh;
  LocalJobContext ctx;
  int64_t flips = 0;
  ASSERT_TRUE(internal::FlipPoorEdges(mesh, &cells, flips, ctx).ok());
  // Every rhombus on either side of the fold is flipped to its short diagonal.
  const double h = std::sqrt(3.0) / 4, degrees = 180 / std::numbers::pi;
  EXPECT_EQ(flips, (size - 1) * (size - 1));
  EXPECT_NEAR(MeasureTriangleQuality(before).min_angle_p1, std::atan(h / 1.5) * degrees, 0.01);
  EXPECT_NEAR(MeasureTriangleQuality(mesh).min_angle_p1, std::atan(2 * h) * degrees, 0.01);
  EXPECT_EQ(mesh.vertices, before.vertices);
  EXPECT_EQ(mesh.faces.size(), before.faces.size());
  const MeshTopology a = AnalyzeTopology(before), b = AnalyzeTopology(mesh);
  EXPECT_EQ(b.boundary_edges, a.boundary_edges);
  EXPECT_EQ(b.non_manifold_edges, 0);
  EXPECT_TRUE(b.consistently_oriented());
  EXPECT_EQ(b.euler_characteristic(), a.euler_characteristic());
  // The fold's edges (along the row where the mesh turns by 90°) are all still there.
  const auto edges = Edges(mesh);
  for (int i = 0; i + 1 < size; ++i) {
    const auto first = static_cast<uint32_t>(fold_row * size + i);
    EXPECT_TRUE(edges.contains({first, first + 1})) << i;
  }
  // Faces traced to different cells are never flipped together.
  core::TriangleMesh split = before;
  std::vector<uint64_t> own(split.faces.size());
  for (size_t f = 0; f < own.size(); ++f) own[f] = f;
  ASSERT_TRUE(internal::FlipPoorEdges(split, &own, flips, ctx).ok());
  EXPECT_EQ(flips, 0);
  EXPECT_EQ(split.faces, before.faces);
}

}  // namespace
}  // namespace lsqsurf::extract
