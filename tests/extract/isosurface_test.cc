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

}  // namespace
}  // namespace lsqsurf::extract
