#include "worker/mls/gaussian_mls.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/j1a_isosurface.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;

constexpr GaussianFit kFits[] = {GaussianFit::kAdamsonAlexa, GaussianFit::kKolluri};

std::unique_ptr<GaussianMlsFunction> Build(const core::PointCloud& cloud, GaussianFit fit, double spacing = 0) {
  GaussianMlsParams p;
  p.fit = fit;
  p.spacing = spacing;
  return testing::BuildOrFail(&BuildGaussianMls, cloud, p);
}

const char* Name(GaussianFit fit) { return fit == GaussianFit::kKolluri ? "imls" : "aamls"; }

// Both surfaces lie inside a curved surface by about σ²/2R (the weighted centroid and the mean
// of tangent planes are on the concave side), so on a sphere sampled ever more densely, with σ
// tied to the spacing, the error falls at second order: by ~4 per halving of h.
TEST(GaussianMls, SphereErrorFallsAtSecondOrder) {
  const double radius = 0.5;
  for (GaussianFit fit : kFits) {
    std::vector<double> errors;
    for (size_t n : {2000, 8000, 32000}) {
      auto f = Build(testing::SphereCloud(n, radius, Vec3d(0.1, 0.2, -0.3)), fit);
      ASSERT_TRUE(f);
      errors.push_back(testing::MaxSurfaceError(
          *f, [&](const Vec3d& d) -> Vec3d { return Vec3d(0.1, 0.2, -0.3) + radius * d; }, 300));
    }
    EXPECT_LT(errors[0], 0.02 * radius) << Name(fit);
    EXPECT_LT(errors[1], errors[0] / 3) << Name(fit) << " " << errors[0] << " " << errors[1];
    EXPECT_LT(errors[2], errors[1] / 3) << Name(fit) << " " << errors[1] << " " << errors[2];
  }
}

// The same on a torus (both curvature signs), sampled on a regular grid with exact normals.
TEST(GaussianMls, TorusErrorFallsAtSecondOrder) {
  const double R = 0.3, r = 0.12;
  for (GaussianFit fit : kFits) {
    std::vector<double> errors;
    for (double h : {1.0 / 32, 1.0 / 64, 1.0 / 128}) {
      auto f = Build(testing::TorusGridCloud(R, r, h), fit, 2 * h);
      ASSERT_TRUE(f);
      errors.push_back(testing::MaxTorusError(*f, R, r, 2 * h, 200));
    }
    EXPECT_LT(errors[0], 0.15 * r) << Name(fit);  // σ = 2h is a sixth of the tube radius here.
    EXPECT_LT(errors[1], errors[0] / 3) << Name(fit) << " " << errors[0] << " " << errors[1];
    EXPECT_LT(errors[2], errors[1] / 3) << Name(fit) << " " << errors[1] << " " << errors[2];
  }
}

// The analytic gradient (moving weights included) against central differences of F.
TEST(GaussianMls, GradientIsTheDerivativeOfTheValue) {
  const core::PointCloud torus = testing::TorusCloud(6000, 0.3, 0.12);
  std::mt19937_64 rng(4);
  std::uniform_int_distribution<size_t> pick(0, torus.size() - 1);
  std::normal_distribution<double> g(0, 1);
  for (GaussianFit fit : kFits) {
    auto f = Build(torus, fit);
    ASSERT_TRUE(f);
    const double step = 1e-4 * f->spacing();
    for (int k = 0; k < 40; ++k) {
      const Vec3d x = torus.positions[pick(rng)].cast<double>() + 0.3 * f->spacing() * Vec3d(g(rng), g(rng), g(rng));
      const core::FieldGradient v = f->ValueAndGradient(x);
      ASSERT_TRUE(v.defined) << Name(fit);
      Vec3d numeric;
      for (int a = 0; a < 3; ++a) {
        const Vec3d e = step * Vec3d::Unit(a);
        numeric[a] = (f->Value(x + e).value - f->Value(x - e).value) / (2 * step);
      }
      EXPECT_LT((v.gradient - numeric).norm(), 1e-5 * numeric.norm() + 1e-6) << Name(fit) << " at " << x.transpose();
      EXPECT_NEAR(v.value, f->Value(x).value, 1e-12);
    }
  }
}

TEST(GaussianMls, UndefinedAwayFromTheDataAndClosedMeshOnIt) {
  const core::PointCloud sphere = testing::SphereCloud(5000);
  for (GaussianFit fit : kFits) {
    auto f = Build(sphere, fit);
    ASSERT_TRUE(f);
    EXPECT_TRUE(f->Value(Vec3d(0, 0, 1)).defined);
    EXPECT_FALSE(f->Value(Vec3d(0, 0, 1 + 2 * f->spacing())).defined);  // Beyond the coverage.
    EXPECT_TRUE(std::isnan(f->Value(Vec3d(0, 0, 0)).value));            // No point within reach.
    core::LocalJobContext ctx;
    extract::J1aIsosurfaceParams ip;
    ip.cell_size = 2 * f->spacing();
    auto mesh = extract::ExtractIsosurfaceJ1a(*f, sphere.positions, ip, ctx);
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    const core::MeshTopology t = core::AnalyzeTopology(mesh->mesh);
    EXPECT_TRUE(t.watertight()) << Name(fit);
    EXPECT_EQ(t.euler_characteristic(), 2) << Name(fit);
    EXPECT_NEAR(core::EnclosedVolume(mesh->mesh) / (4.0 / 3.0 * std::numbers::pi), 1.0, 0.02) << Name(fit);
  }
}

// Two parallel sheets 0.2σ apart with opposite normals: their normals cancel in Adamson–Alexa's
// mean, which then has no direction, so no surface is placed between them.
TEST(GaussianMls, AdamsonAlexaIsUndefinedWhereNormalsCancel) {
  const double h = 0.01;
  core::PointCloud cloud;
  for (int i = -20; i <= 20; ++i) {
    for (int j = -20; j <= 20; ++j) {
      for (double side : {-1.0, 1.0}) {
        cloud.positions.push_back(Vec3d(i * h, j * h, side * 0.1 * h).cast<float>());
        cloud.normals.push_back(Vec3d(0, 0, side).cast<float>());
      }
    }
  }
  auto f = Build(cloud, GaussianFit::kAdamsonAlexa, h);
  ASSERT_TRUE(f);
  EXPECT_FALSE(f->Value(Vec3d(0.003, -0.002, 0.0)).defined);
}

TEST(GaussianMls, RejectsBadInput) {
  core::LocalJobContext ctx;
  core::PointCloud bare = testing::SphereCloud(100);
  bare.normals.clear();
  EXPECT_EQ(BuildGaussianMls(bare, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  core::PointCloud nan = testing::SphereCloud(100);
  nan.positions[7].x() = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(BuildGaussianMls(nan, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  core::PointCloud zero_normal = testing::SphereCloud(100);
  zero_normal.normals[3] = core::Vec3f::Zero();
  EXPECT_EQ(BuildGaussianMls(zero_normal, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  core::PointCloud one_place(testing::SphereCloud(10));
  for (auto& p : one_place.positions) p = core::Vec3f(1, 2, 3);
  EXPECT_EQ(BuildGaussianMls(one_place, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  GaussianMlsParams p;
  p.width = 0.1;
  EXPECT_EQ(BuildGaussianMls(testing::SphereCloud(100), p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::mls
