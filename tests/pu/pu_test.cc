#include "worker/pu/pu.h"

#include <gtest/gtest.h>

#include <random>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"

namespace lsqsurf::pu {
namespace {

using core::Vec3d;

std::unique_ptr<PuFunction> Build(const core::PointCloud& cloud, PuParams p = {}) {
  core::LocalJobContext ctx;
  auto f = BuildPu(cloud, p, ctx);
  EXPECT_TRUE(f.ok()) << f.status();
  return f.ok() ? *std::move(f) : nullptr;
}

core::TriangleMesh ExtractMesh(const PuFunction& f, PuExtractParams p = {}) {
  core::LocalJobContext ctx;
  auto r = Extract(f, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? std::move(r->mesh) : core::TriangleMesh{};
}

// Largest |F| / |∇F| at random points of the true surface given by `project`.
template <class Project>
double MaxSurfaceError(const PuFunction& f, Project project) {
  std::mt19937_64 rng(17);
  std::normal_distribution<double> g(0, 1);
  double worst = 0;
  for (int i = 0; i < 500; ++i) {
    const Vec3d x = project(Vec3d(g(rng), g(rng), g(rng)).normalized());
    const core::FieldGradient v = f.ValueAndGradient(x);
    EXPECT_TRUE(v.defined) << x.transpose();
    worst = std::max(worst, std::abs(v.value) / v.gradient.norm());
  }
  return worst;
}

// Largest distance of a mesh vertex from the unit sphere.
double MaxSphereDeviation(const core::TriangleMesh& mesh) {
  double worst = 0;
  for (const auto& v : mesh.vertices) worst = std::max(worst, std::abs(v.cast<double>().norm() - 1.0));
  return worst;
}

TEST(Pu, SphereFieldIsSignedAndAccurate) {
  auto f = Build(testing::SphereCloud(20000));
  ASSERT_TRUE(f);
  EXPECT_LT(MaxSurfaceError(*f, [](const Vec3d& d) { return d; }), 2e-4);
  // Signs inside and outside, near the surface and across the volume.
  EXPECT_LT(f->Value(Vec3d(0, 0, 0.9)).value, 0);
  EXPECT_GT(f->Value(Vec3d(0, 0, 1.1)).value, 0);
  EXPECT_NEAR(f->Value(Vec3d(0.95, 0, 0)).value, -0.05, 0.01);
  const core::FieldGradient g = f->ValueAndGradient(Vec3d(0, 0.6, 0.8));
  EXPECT_NEAR(g.gradient.normalized().dot(Vec3d(0, 0.6, 0.8)), 1.0, 1e-3);
}

TEST(Pu, GradientMatchesFiniteDifferences) {
  auto f = Build(testing::SphereCloud(5000));
  ASSERT_TRUE(f);
  const double h = 1e-6;
  for (const Vec3d& x : {Vec3d(0.3, 0.4, 0.85), Vec3d(-0.7, 0.1, -0.65), Vec3d(0.05, -0.98, 0.1)}) {
    const core::FieldGradient g = f->ValueAndGradient(x);
    for (int k = 0; k < 3; ++k) {
      const Vec3d e = Vec3d::Unit(k) * h;
      const double fd = (f->Value(x + e).value - f->Value(x - e).value) / (2 * h);
      EXPECT_NEAR(g.gradient[k], fd, 1e-5 * (1 + std::abs(fd))) << x.transpose() << " axis " << k;
    }
  }
}

TEST(Pu, SphereMeshIsClosedGenusZeroAndWithinABoundThatShrinksWithDensity) {
  // The error threshold follows the sampling density; the distance of the mesh to the exact
  // sphere must stay below it (the diagonal of the cloud's box is 2√3).
  const double diagonal = 2 * std::sqrt(3.0);
  for (const auto& [n, threshold] : {std::pair{3000, 1e-3}, std::pair{12000, 2.5e-4}, std::pair{48000, 6e-5}}) {
    PuParams params;
    params.error_threshold = threshold;
    auto f = Build(testing::SphereCloud(static_cast<size_t>(n)), params);
    ASSERT_TRUE(f);
    const core::TriangleMesh mesh = ExtractMesh(*f);
    const core::MeshTopology topo = core::AnalyzeTopology(mesh);
    EXPECT_EQ(topo.boundary_edges, 0) << n;
    EXPECT_EQ(topo.non_manifold_edges, 0) << n;
    EXPECT_EQ(topo.components, 1) << n;
    EXPECT_EQ(topo.euler_characteristic(), 2) << n;
    EXPECT_LT(MaxSphereDeviation(mesh), threshold * diagonal) << n;
    EXPECT_NEAR(core::EnclosedVolume(mesh), 4.0 / 3.0 * M_PI, 0.01) << n;
  }
}

}  // namespace
}  // namespace lsqsurf::pu
