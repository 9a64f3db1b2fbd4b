#include "worker/mls/iamls.h"

#include <gtest/gtest.h>

#include <numbers>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;

std::unique_ptr<IamlsFunction> Build(const core::PointCloud& cloud, IamlsParams p = {}) {
  return testing::BuildOrFail(&BuildIamls, cloud, p);
}

TEST(Iamls, SphereErrorIsSmallAndShrinksWithDensity) {
  double previous = 1e9;
  for (size_t n : {2000, 8000, 32000}) {
    auto f = Build(testing::SphereCloud(n));
    ASSERT_TRUE(f);
    const double err = testing::MaxSurfaceError(
        *f, [](const Vec3d& d) { return d; }, 300);
    EXPECT_LT(err, 0.01) << n;  // Radius 1.
    EXPECT_LT(err, previous) << n;
    previous = err;
  }
}

TEST(Iamls, TorusErrorShrinksWithDensity) {
  const double R = 1.0, r = 0.35;
  auto on_torus = [&](const Vec3d& d) {
    const double theta = std::atan2(d.y(), d.x()), phi = std::asin(d.z()) * 2;
    return Vec3d((R + r * std::cos(phi)) * std::cos(theta), (R + r * std::cos(phi)) * std::sin(theta),
                 r * std::sin(phi));
  };
  auto coarse = Build(testing::TorusCloud(10000, R, r));
  auto fine = Build(testing::TorusCloud(40000, R, r));
  ASSERT_TRUE(coarse && fine);
  const double e_coarse = testing::MaxSurfaceError(*coarse, on_torus, 300);
  const double e_fine = testing::MaxSurfaceError(*fine, on_torus, 300);
  EXPECT_LT(e_fine, e_coarse);
  EXPECT_LT(e_fine, 0.01 * r);
}

TEST(Iamls, IterationsReduceTheResidualAtTheSamples) {
  IamlsParams p;
  p.iterations = 5;
  auto f = Build(testing::TorusCloud(8000, 1.0, 0.35), p);
  ASSERT_TRUE(f);
  const auto& res = f->stats().residuals;
  ASSERT_EQ(res.size(), 6u);
  EXPECT_LT(res.back(), res.front());
}

TEST(Iamls, NoSurfaceOnTheGhostSheet) {
  // F⁽⁰⁾ has spurious zeros where ΣΨ turns negative (~1.22 h/ε off the data): they must be
  // reported undefined.
  IamlsParams p;
  p.iterations = 0;
  p.min_weight = 0;  // Only the sign of ΣΨ decides: F is then still defined inside the band.
  auto f = Build(testing::SphereCloud(4000), p);
  ASSERT_TRUE(f);
  const double h = f->spacing();
  const double ghost = 1.0 + std::sqrt(1.5) * h / p.epsilon;
  EXPECT_TRUE(f->Value(Vec3d(1.0, 0, 0)).defined);
  EXPECT_FALSE(f->Value(Vec3d(ghost + 0.3 * h, 0, 0)).defined);
}

TEST(Iamls, ReconstructsAClosedSphereOfTheRightVolume) {
  const auto cloud = testing::SphereCloud(20000);
  auto f = Build(cloud);
  ASSERT_TRUE(f);
  core::LocalJobContext ctx;
  extract::IsosurfaceParams xp;
  xp.cell_size = 1.5 * f->spacing();
  auto mesh = extract::ExtractIsosurface(*f, cloud.positions, xp, ctx);
  ASSERT_TRUE(mesh.ok());
  const core::MeshTopology t = core::AnalyzeTopology(mesh->mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_EQ(t.euler_characteristic(), 2);
  EXPECT_NEAR(core::EnclosedVolume(mesh->mesh) / (4.0 / 3.0 * std::numbers::pi), 1.0, 0.01);
}

TEST(Iamls, RejectsBadParametersWithActionableMessages) {
  core::LocalJobContext ctx;
  const auto cloud = testing::SphereCloud(3000);
  IamlsParams p;
  p.epsilon = 2.5;
  auto diverging = BuildIamls(cloud, p, ctx);
  ASSERT_EQ(diverging.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(diverging.status().message()).find("diverge"), std::string::npos);
  p.epsilon = -1;
  EXPECT_EQ(BuildIamls(cloud, p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  core::PointCloud no_normals = cloud;
  no_normals.normals.clear();
  EXPECT_EQ(BuildIamls(no_normals, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::mls
