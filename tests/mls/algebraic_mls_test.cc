#include "worker/mls/algebraic_mls.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/isosurface.h"
#include "worker/extract/j1a_isosurface.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;

std::unique_ptr<AlgebraicMlsFunction> Build(const core::PointCloud& cloud, AlgebraicMlsParams p = {}) {
  return testing::BuildOrFail(&BuildAlgebraicMls, cloud, p);
}

// The planes z = ±half sampled on a grid of step h, with normals facing·(0, 0, ±1) (facing 1:
// out of the slab between them). The lower plane is shifted by half a step so that the two do
// not pair up.
core::PointCloud PlanePair(double h, double half, double facing) {
  core::PointCloud cloud;
  for (int i = -20; i <= 20; ++i) {
    for (int j = -20; j <= 20; ++j) {
      for (double side : {-1.0, 1.0}) {
        const double shift = side < 0 ? 0.5 * h : 0;
        cloud.positions.push_back(Vec3d(i * h + shift, j * h + shift, side * half).cast<float>());
        cloud.normals.push_back(Vec3d(0, 0, facing * side).cast<float>());
      }
    }
  }
  return cloud;
}

TEST(AlgebraicMls, BothFitsReproduceASphereExactly) {
  for (AlgebraicFit fit : {AlgebraicFit::kRamls, AlgebraicFit::kApss}) {
    AlgebraicMlsParams p;
    p.fit = fit;
    auto f = Build(testing::SphereCloud(4000, 0.5, Vec3d(0.2, -0.1, 0.3)), p);
    ASSERT_TRUE(f);
    std::mt19937_64 rng(1);
    std::normal_distribution<double> g;
    for (int k = 0; k < 50; ++k) {
      const Vec3d d = Vec3d(g(rng), g(rng), g(rng)).normalized();
      for (double offset : {-0.3, 0.0, 0.5}) {
        // Within the band where the support holds points, F is the Pratt-normalized value of
        // the exact sphere, (ρ² − r²) / 2r at distance ρ from its centre.
        const double rho = 0.5 + offset * f->spacing();
        const core::FieldGradient v = f->ValueAndGradient(Vec3d(0.2, -0.1, 0.3) + rho * d);
        ASSERT_TRUE(v.defined);
        EXPECT_NEAR(v.value, (rho * rho - 0.25) / 1.0, 1e-6) << static_cast<int>(fit);  // Float positions.
        // The sphere's own gradient: along d, of length ρ / r.
        EXPECT_NEAR(v.gradient.dot(d), rho / 0.5, 1e-5);
        EXPECT_NEAR(v.gradient.cross(d).norm(), 0.0, 1e-5);
      }
    }
  }
}

// A slab far thinner than the support: the planes z = ±0.1h, sampled on a grid of step h with
// outward normals ±z. Fitted to one face each, the value is the exact signed distance to that
// face and the gradient its normal, however close the other face is.
TEST(AlgebraicMls, FacingFitKeepsTheTwoFacesOfAThinSheetApart) {
  const double h = 0.01, half = 0.1 * h;
  const core::PointCloud cloud = PlanePair(h, half, 1.0);
  AlgebraicMlsParams p;
  p.spacing = h;
  auto f = Build(cloud, p);
  ASSERT_TRUE(f);
  for (const Vec3d& x : {Vec3d(0.013, -0.021, 0.0), Vec3d(-0.04, 0.05, 0.3 * h), Vec3d(0.07, 0.002, -1.2 * h)}) {
    for (double side : {-1.0, 1.0}) {
      const core::FieldGradient one = f->ValueAndGradientFacing(x, Vec3d(0.2, -0.1, side), 0.0);
      ASSERT_TRUE(one.defined) << x.transpose();
      EXPECT_NEAR(one.value, side * (x.z() - side * half), 1e-6) << x.transpose() << " side " << side;
      EXPECT_NEAR(one.gradient.z(), side, 1e-6);
      EXPECT_NEAR(one.gradient.head<2>().norm(), 0.0, 1e-6);
    }
  }
  // Facing away from every point: nothing to fit.
  EXPECT_FALSE(f->ValueAndGradientFacing(Vec3d::Zero(), Vec3d(1, 0, 0), 0.5).defined);
}

// Sides(): two planes z = ±g/2 (g < the support), sampled like the sheet above. With normals
// facing each other (a gap between two fronts) or away from each other (the walls of a slab),
// the near fit is the nearer plane's signed distance, the far fit the other's, and far_in_front
// tells the gap from the slab.
TEST(AlgebraicMls, SidesSeparatesAGapFromASlab) {
  const double h = 0.01, half = 0.6 * h;
  for (double facing : {-1.0, 1.0}) {  // −1: normals point into the gap; +1: out of the slab.
    const core::PointCloud cloud = PlanePair(h, half, facing);
    AlgebraicMlsParams p;
    p.spacing = h;
    p.side_cosine = -0.5;
    auto f = Build(cloud, p);
    ASSERT_TRUE(f);
    for (double z : {-0.4 * h, 0.2 * h, 0.9 * h}) {
      const Vec3d x(0.013, -0.021, z);
      const SidesAt s = f->Sides(x);
      ASSERT_TRUE(s.near.defined && s.far.defined) << z;
      const double near_side = z >= 0 ? 1 : -1;  // The plane nearer x.
      // Signed distance to the plane at side·half with outward normal facing·side·z.
      auto distance = [&](double side) { return facing * side * (z - side * half); };
      EXPECT_NEAR(s.near.value, distance(near_side), 1e-6) << facing << " " << z;
      EXPECT_NEAR(s.far.value, distance(-near_side), 1e-6) << facing << " " << z;
      EXPECT_EQ(s.far_in_front, facing < 0) << facing << " " << z;
    }
  }
}

// METHODS.md §2.6: the RAMLS surface of a torus converges at about second order as h halves.
TEST(AlgebraicMls, RamlsTorusErrorFallsAtAboutSecondOrder) {
  const double R = 0.3, r = 0.12;
  std::vector<double> errors;
  for (double h : {1.0 / 32, 1.0 / 64, 1.0 / 128}) {
    AlgebraicMlsParams p;
    p.spacing = h;
    auto f = Build(testing::TorusGridCloud(R, r, h), p);
    ASSERT_TRUE(f);
    errors.push_back(testing::MaxTorusError(*f, R, r, h, 200));
  }
  EXPECT_LT(errors[0], 1e-3);
  EXPECT_LT(errors[1], errors[0] / 2.5) << errors[0] << " " << errors[1];
  EXPECT_LT(errors[2], errors[1] / 2.5) << errors[1] << " " << errors[2];
}

// RAMLS is APSS's β → ∞ limit; a small β lets positions outweigh normals, which on points with
// wrong normals keeps the surface on the points.
TEST(AlgebraicMls, ApssApproachesRamlsAsBetaGrows) {
  const core::PointCloud torus = testing::TorusGridCloud(0.3, 0.12, 1.0 / 64);
  AlgebraicMlsParams ramls;
  ramls.spacing = 1.0 / 64;
  AlgebraicMlsParams apss = ramls;
  apss.fit = AlgebraicFit::kApss;
  auto fr = Build(torus, ramls);
  double previous = std::numeric_limits<double>::infinity();
  for (double beta : {1e-2, 1.0, 1e2, 1e6}) {
    apss.apss_beta = beta;
    auto fa = Build(torus, apss);
    ASSERT_TRUE(fr && fa);
    double gap = 0;
    for (int k = 0; k < 100; ++k) {
      const double t = 0.0628 * k;
      const Vec3d x(0.42 * std::cos(t), 0.42 * std::sin(t), 0.01 * std::sin(3 * t));
      gap = std::max(gap, std::abs(fa->Value(x).value - fr->Value(x).value));
    }
    EXPECT_LT(gap, previous) << beta;
    previous = gap;
  }
  EXPECT_LT(previous, 1e-6);
}

TEST(AlgebraicMls, UndefinedAwayFromTheDataAndClosedMeshOnIt) {
  auto f = Build(testing::SphereCloud(3000));
  ASSERT_TRUE(f);
  EXPECT_TRUE(f->Value(Vec3d(0, 0, 1)).defined);
  EXPECT_FALSE(f->Value(Vec3d(0, 0, 1 + 2 * f->spacing())).defined);  // Beyond the coverage.
  EXPECT_FALSE(f->Value(Vec3d(0, 0, 0)).defined);                     // No support at all.
  core::LocalJobContext ctx;
  extract::J1aIsosurfaceParams ip;
  ip.cell_size = 2 * f->spacing();
  ip.marching.refine_steps = 12;  // Converged roots, so that the check below sees F itself.
  auto mesh = extract::ExtractIsosurfaceJ1a(*f, testing::SphereCloud(3000).positions, ip, ctx);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  const core::MeshTopology t = core::AnalyzeTopology(mesh->mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_EQ(t.euler_characteristic(), 2);
  // Vertices are roots of F, which is exact here; the volume is short by the chords only.
  for (const auto& v : mesh->mesh.vertices) EXPECT_NEAR(v.cast<double>().norm(), 1.0, 1e-5);
  EXPECT_NEAR(core::EnclosedVolume(mesh->mesh) / (4.0 / 3.0 * std::numbers::pi), 1.0, 0.01);
}

TEST(AlgebraicMls, RejectsBadInput) {
  core::LocalJobContext ctx;
  core::PointCloud bare = testing::SphereCloud(100);
  bare.normals.clear();
  EXPECT_EQ(BuildAlgebraicMls(bare, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  core::PointCloud nan = testing::SphereCloud(100);
  nan.positions[7].x() = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(BuildAlgebraicMls(nan, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  AlgebraicMlsParams p;
  p.fit = AlgebraicFit::kApss;
  p.apss_beta = 0;
  EXPECT_EQ(BuildAlgebraicMls(testing::SphereCloud(100), p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  p = {};
  p.support_factor = 0.5;
  EXPECT_EQ(BuildAlgebraicMls(testing::SphereCloud(100), p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::mls
