#include "worker/core/isosurface.h"

#include <gtest/gtest.h>

#include <numbers>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"

namespace lsqsurf::core {
namespace {

IsosurfaceResult Extract(const ImplicitFunction& f, const PointCloud& seeds, double cell) {
  LocalJobContext ctx;
  IsosurfaceParams p;
  p.cell_size = cell;
  auto r = ExtractIsosurface(f, seeds.positions, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? *std::move(r) : IsosurfaceResult{};
}

TEST(Isosurface, SphereIsClosedWithExactTopologyAndVolume) {
  const testing::SphereField sphere(1.0);
  const auto r = Extract(sphere, testing::SphereCloud(2000), 0.05);
  const MeshTopology t = AnalyzeTopology(r.mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_TRUE(t.consistently_oriented());
  EXPECT_EQ(t.euler_characteristic(), 2);
  EXPECT_EQ(t.components, 1);
  const double exact = 4.0 / 3.0 * std::numbers::pi;
  EXPECT_NEAR(EnclosedVolume(r.mesh) / exact, 1.0, 0.01);  // Positive: outward orientation.
  for (const auto& v : r.mesh.vertices) EXPECT_NEAR(v.cast<double>().norm(), 1.0, 1e-5);  // Linear interpolation alone: ~1e-4.
}

TEST(Isosurface, TorusHasGenusOne) {
  const testing::TorusField torus(1.0, 0.35);
  const auto r = Extract(torus, testing::TorusCloud(4000, 1.0, 0.35), 0.04);
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

TEST(Isosurface, NothingWhereTheFieldIsUnknown) {
  const HalfKnownSphere field;
  const auto r = Extract(field, testing::SphereCloud(2000), 0.05);
  ASSERT_FALSE(r.mesh.faces.empty());
  for (const auto& v : r.mesh.vertices) EXPECT_LE(v.z(), 0.3f + 1e-5f);
  EXPECT_GT(AnalyzeTopology(r.mesh).boundary_edges, 0);  // Open where the field stops.
}

TEST(Isosurface, RejectsBadParametersAndHonoursCancellation) {
  const testing::SphereField sphere(1.0);
  const auto seeds = testing::SphereCloud(100);
  LocalJobContext ctx;
  IsosurfaceParams p;
  EXPECT_EQ(ExtractIsosurface(sphere, seeds.positions, p, ctx).status().code(),
            absl::StatusCode::kInvalidArgument);
  p.cell_size = 0.01;
  p.max_cells = 1000;
  EXPECT_EQ(ExtractIsosurface(sphere, seeds.positions, p, ctx).status().code(),
            absl::StatusCode::kResourceExhausted);
  p.max_cells = 60'000'000;
  ctx.Cancel();
  EXPECT_EQ(ExtractIsosurface(sphere, seeds.positions, p, ctx).status().code(),
            absl::StatusCode::kCancelled);
}

}  // namespace
}  // namespace lsqsurf::core
