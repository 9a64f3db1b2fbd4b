#include "worker/extract/isosurface.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <numbers>
#include <utility>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/j1a_isosurface.h"

namespace lsqsurf::extract {
namespace {

using namespace ::lsqsurf::core;  // The tests speak in core types throughout.

// Both extractors, behind one signature, so that the shared properties are tested once.
using Extractor = IsosurfaceResult (*)(const ImplicitFunction&, const PointCloud&, double cell);

template <class Params, absl::StatusOr<IsosurfaceResult> (*kExtract)(const ImplicitFunction&, std::span<const Vec3f>,
                                                                     const Params&, JobContext&)>
IsosurfaceResult Run(const ImplicitFunction& f, const PointCloud& seeds, double cell) {
  LocalJobContext ctx;
  Params p;
  p.cell_size = cell;
  auto r = kExtract(f, seeds.positions, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? *std::move(r) : IsosurfaceResult{};
}
constexpr Extractor Uniform = &Run<IsosurfaceParams, &ExtractIsosurface>;
constexpr Extractor J1a = &Run<J1aIsosurfaceParams, &ExtractIsosurfaceJ1a>;

class EveryExtractor : public ::testing::TestWithParam<Extractor> {};

TEST_P(EveryExtractor, SphereIsClosedWithExactTopologyAndVolume) {
  const testing::SphereField sphere(1.0);
  const auto r = GetParam()(sphere, testing::SphereCloud(2000), 0.05);
  const MeshTopology t = AnalyzeTopology(r.mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_TRUE(t.consistently_oriented());
  EXPECT_EQ(t.euler_characteristic(), 2);
  EXPECT_EQ(t.components, 1);
  const double exact = 4.0 / 3.0 * std::numbers::pi;
  EXPECT_NEAR(EnclosedVolume(r.mesh) / exact, 1.0, 0.01);  // Positive: outward orientation.
  // Refined roots; linear interpolation alone would be off by ~1e-4.
  for (const auto& v : r.mesh.vertices) EXPECT_NEAR(v.cast<double>().norm(), 1.0, 1e-5);
}

TEST_P(EveryExtractor, TorusHasGenusOne) {
  const testing::TorusField torus(1.0, 0.35);
  const auto r = GetParam()(torus, testing::TorusCloud(4000, 1.0, 0.35), 0.04);
  const MeshTopology t = AnalyzeTopology(r.mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_TRUE(t.consistently_oriented());
  EXPECT_EQ(t.euler_characteristic(), 0);
  const double exact = 2 * std::numbers::pi * std::numbers::pi * 1.0 * 0.35 * 0.35;
  EXPECT_NEAR(EnclosedVolume(r.mesh) / exact, 1.0, 0.01);
}

// A field that is unknown (NaN) on one side of a plane: nothing may be placed there.
class HalfKnownSphere : public ImplicitFunction {
 public:
  FieldValue Value(const Vec3d& x) const override {
    if (x.z() > 0.3) return {std::numeric_limits<double>::quiet_NaN(), false};
    return {x.norm() - 1.0, true};
  }
  FieldGradient ValueAndGradient(const Vec3d& x) const override {
    const FieldValue v = Value(x);
    return {v.value, x.normalized(), v.defined};
  }
};

TEST_P(EveryExtractor, NothingWhereTheFieldIsUnknown) {
  const HalfKnownSphere field;
  const auto r = GetParam()(field, testing::SphereCloud(2000), 0.05);
  ASSERT_FALSE(r.mesh.faces.empty());
  for (const auto& v : r.mesh.vertices) EXPECT_LE(v.z(), 0.3f + 1e-5f);
  EXPECT_GT(AnalyzeTopology(r.mesh).boundary_edges, 0);  // Open where the field stops.
}

// A unit sphere whose field is untrusted (`defined` false, value still right) in a band around
// the north pole, 0.05 < polar angle < 0.45, and in a small spot around the south pole.
class SphereWithUntrustedBand : public ImplicitFunction {
 public:
  FieldValue Value(const Vec3d& x) const override { return {x.norm() - 1.0, Trusted(x)}; }
  FieldGradient ValueAndGradient(const Vec3d& x) const override { return {x.norm() - 1.0, x.normalized(), Trusted(x)}; }
  static double PolarAngle(const Vec3d& x) { return std::acos(std::clamp(x.z() / x.norm(), -1.0, 1.0)); }

 private:
  static bool Trusted(const Vec3d& x) {
    const double angle = PolarAngle(x);
    return !(angle > 0.05 && angle < 0.45) && angle < std::numbers::pi - 0.02;
  }
};

// Edges used by one triangle only, with both ends below height z.
int BoundaryEdgesBelow(const TriangleMesh& mesh, float z) {
  std::map<std::pair<uint32_t, uint32_t>, int> uses;
  for (const Triangle& f : mesh.faces) {
    for (int i = 0; i < 3; ++i) {
      const uint32_t a = f[static_cast<size_t>(i)], b = f[static_cast<size_t>((i + 1) % 3)];
      ++uses[std::minmax(a, b)];
    }
  }
  int count = 0;
  for (const auto& [edge, n] : uses)
    count += n == 1 && mesh.vertices[edge.first].z() < z && mesh.vertices[edge.second].z() < z;
  return count;
}

// The band is far larger than a pinhole, so it is dropped; the trusted cap inside it is a speck
// cut off from the surface and goes with it; the south spot is a pinhole and is filled.
TEST_P(EveryExtractor, DropsCutOffSpecksAndFillsPinholes) {
  const SphereWithUntrustedBand field;
  const auto r = GetParam()(field, testing::SphereCloud(2000), 0.05);
  ASSERT_FALSE(r.mesh.faces.empty());
  for (const auto& v : r.mesh.vertices) {
    EXPECT_GT(SphereWithUntrustedBand::PolarAngle(v.cast<double>()), 0.45 - 0.06);  // Within a cell of the band.
  }
  EXPECT_EQ(BoundaryEdgesBelow(r.mesh, -0.9f), 0);  // The pinhole at the south pole is closed.
  const MeshTopology t = AnalyzeTopology(r.mesh);
  EXPECT_EQ(t.components, 1);
  EXPECT_GT(t.boundary_edges, 0);
  EXPECT_EQ(t.non_manifold_edges, 0);
}

TEST(J1aIsosurface, KeepsSpecksAndPinholesOpenWhenAskedTo) {
  const SphereWithUntrustedBand field;
  LocalJobContext ctx;
  J1aIsosurfaceParams p;
  p.cell_size = 0.05;
  p.marching.max_patch_triangles = 0;
  auto r = ExtractIsosurfaceJ1a(field, testing::SphereCloud(2000).positions, p, ctx);
  ASSERT_TRUE(r.ok()) << r.status();
  double smallest_angle = 1;
  for (const auto& v : r->mesh.vertices) {
    smallest_angle = std::min(smallest_angle, SphereWithUntrustedBand::PolarAngle(v.cast<double>()));
  }
  EXPECT_GT(BoundaryEdgesBelow(r->mesh, -0.9f), 0);   // The pinhole stays open.
  EXPECT_LT(smallest_angle, 0.05);                    // The cap stays,
  EXPECT_EQ(AnalyzeTopology(r->mesh).components, 2);  // as a second piece.
}

INSTANTIATE_TEST_SUITE_P(UniformAndJ1a, EveryExtractor, ::testing::Values(Uniform, J1a));

TEST(Isosurface, RejectsBadParametersAndHonoursCancellation) {
  const testing::SphereField sphere(1.0);
  const auto seeds = testing::SphereCloud(100);
  LocalJobContext ctx;
  IsosurfaceParams p;
  EXPECT_EQ(ExtractIsosurface(sphere, seeds.positions, p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  p.cell_size = 0.01;
  p.max_cells = 1000;
  EXPECT_EQ(ExtractIsosurface(sphere, seeds.positions, p, ctx).status().code(), absl::StatusCode::kResourceExhausted);
  p.max_cells = 60'000'000;
  ctx.Cancel();
  EXPECT_EQ(ExtractIsosurface(sphere, seeds.positions, p, ctx).status().code(), absl::StatusCode::kCancelled);
}

// Seeds cover only part of the surface: tracking leaves the refined band and carries on through
// coarser leaves, and the result is still closed. (Two far seeds make the tree span the sphere.)
TEST(J1aIsosurface, FollowsTheSurfaceIntoCoarseLeaves) {
  const testing::SphereField sphere(1.0);
  PointCloud cap;
  for (const auto& p : testing::SphereCloud(4000).positions) {
    if (p.z() > 0.8f) cap.positions.push_back(p);
  }
  cap.positions.emplace_back(-1.3f, -1.3f, -1.3f);
  cap.positions.emplace_back(1.3f, 1.3f, 1.3f);
  const auto r = J1a(sphere, cap, 0.05);
  const MeshTopology t = AnalyzeTopology(r.mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_EQ(t.euler_characteristic(), 2);
  EXPECT_NEAR(EnclosedVolume(r.mesh) / (4.0 / 3.0 * std::numbers::pi), 1.0, 0.1);
  // Coarse leaves away from the cap: far fewer triangles below than above.
  size_t below = 0, above = 0;
  for (const auto& v : r.mesh.vertices) (v.z() < 0 ? below : above)++;
  EXPECT_LT(below * 4, above);
}

TEST(J1aIsosurface, ChordEstimateFollowsTheCurvature) {
  // On a sphere of radius r the flat chords of cells of edge e stray by κ ℓ² / 8 with κ = 1/r and
  // ℓ = e / 2 (the estimate's typical J1a triangle edge); on a plane by nothing.
  for (const double r : {0.5, 1.0, 2.0}) {
    const testing::SphereField sphere(r);
    for (const double e : {0.02, 0.1}) {
      const double expected = (1 / r) * (e / 2) * (e / 2) / 8;
      // From a point off the surface: the estimate measures at the nearest surface point.
      EXPECT_NEAR(EstimateChordError(sphere, Vec3d(0.3, -0.2, r + 0.4 * e).normalized() * (r + 0.4 * e), e), expected,
                  0.02 * expected)
          << "r=" << r << " e=" << e;
    }
  }
  struct Plane : ImplicitFunction {
    FieldValue Value(const Vec3d& x) const override { return {x.dot(Vec3d(1, 2, 2)) / 3, true}; }
    FieldGradient ValueAndGradient(const Vec3d& x) const override { return {Value(x).value, Vec3d(1, 2, 2) / 3, true}; }
  };
  EXPECT_NEAR(EstimateChordError(Plane{}, Vec3d(0.1, 0.2, 0.3), 0.1), 0.0, 1e-12);
  // Where ∇F vanishes nothing can be said: split.
  EXPECT_TRUE(std::isinf(EstimateChordError(testing::SphereField(1.0), Vec3d::Zero(), 0.1)));
}

TEST(J1aIsosurface, RefinesTheBandOnlyUntilTheChordsAreCloseEnough) {
  const testing::SphereField sphere(1.0);
  const PointCloud seeds = testing::SphereCloud(20000);
  constexpr int kCoarse = 4, kFinest = 7;
  AdaptiveOctree tree(Box3(Vec3d::Constant(-1.5), Vec3d::Constant(1.5)), kFinest);
  const SurfaceBand coarse = MarkSurfaceBand(tree, seeds.positions, kCoarse);
  const SurfaceBand fine = MarkSurfaceBand(tree, seeds.positions, kFinest);
  // Edges 3/32 (chord 2.7e-4, split), 3/64 (6.9e-5, kept) and 3/128 on the unit sphere.
  const double bound = 2e-4;
  LocalJobContext ctx;
  ASSERT_TRUE(RefineSurfaceBand(
                  tree, coarse, kCoarse, fine,
                  [&](const OctreeCell& c) {
                    return EstimateChordError(sphere, tree.CellCentre(c), tree.CellEdge(c.level)) > bound;
                  },
                  ctx)
                  .ok());
  tree.Balance();
  std::map<int, int> leaves_per_level;
  for (const OctreeCell& c : tree.Leaves()) {
    if (std::abs(tree.CellCentre(c).norm() - 1) < tree.CellEdge(c.level)) ++leaves_per_level[c.level];
  }
  EXPECT_EQ(leaves_per_level.count(kFinest), 0u);
  EXPECT_EQ(leaves_per_level.count(kCoarse), 0u);
  EXPECT_GT(leaves_per_level[kFinest - 1], 1000);
  std::vector<OctreeCell> start;
  for (uint64_t key : fine.occupied) start.push_back(CellFromKey(key));
  auto r = ExtractIsosurfaceOnTree(sphere, tree, start, 10'000'000, MarchingOptions{}, ctx);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(AnalyzeTopology(r->mesh).watertight());
  // What the bound promises: the triangles' centroids stray by less (the estimate at the kept
  // level is 6.9e-5: the mean stray is about half of it, the largest about twice).
  double sum = 0, worst = 0;
  for (const Triangle& t : r->mesh.faces) {
    const Vec3d c = (r->mesh.vertices[t[0]] + r->mesh.vertices[t[1]] + r->mesh.vertices[t[2]]).cast<double>() / 3;
    const double stray = std::abs(c.norm() - 1);
    sum += stray;
    worst = std::max(worst, stray);
  }
  const double mean = sum / static_cast<double>(r->mesh.faces.size());
  EXPECT_LT(mean, bound / 2);
  EXPECT_LT(worst, bound);
  std::printf("chord bound %.1e: mean stray %.2e, largest %.2e\n", bound, mean, worst);
}

}  // namespace
}  // namespace lsqsurf::extract
