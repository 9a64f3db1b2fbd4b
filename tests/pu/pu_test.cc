#include "worker/pu/pu.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <limits>
#include <numbers>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/kd_tree.h"
#include "worker/core/mesh_metrics.h"

namespace lsqsurf::pu {
namespace {

using core::Vec3d;

std::unique_ptr<PuFunction> Build(const core::PointCloud& cloud, PuParams p = {}) {
  return testing::BuildOrFail(&BuildPu, cloud, p);
}

core::TriangleMesh ExtractMesh(const PuFunction& f, PuExtractParams p = {}) {
  core::LocalJobContext ctx;
  auto r = Extract(f, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? std::move(r->mesh) : core::TriangleMesh{};
}

// Largest distance of a mesh vertex from the unit sphere.
double MaxSphereDeviation(const core::TriangleMesh& mesh) {
  double worst = 0;
  for (const auto& v : mesh.vertices) worst = std::max(worst, std::abs(v.cast<double>().norm() - 1.0));
  return worst;
}

// A drilled block (creases and a hole, so relaxation, crease splits and flips all act) extracted
// three times from one function gives one mesh, numbering included. Tracking once started from
// leaves in a hash set's order, which absl changes from table to table: the numbering varied and
// the order-dependent steps after marching (flips, relaxation sums) moved vertices with it.
TEST(Pu, ExtractionIsTheSameOnEveryRun) {
  auto f = Build(testing::DrilledBlockCloud(40000));
  ASSERT_TRUE(f);
  const core::TriangleMesh first = ExtractMesh(*f);
  ASSERT_GT(first.faces.size(), 1000u);
  for (int run = 0; run < 2; ++run) {
    const core::TriangleMesh again = ExtractMesh(*f);
    EXPECT_EQ(again.vertices, first.vertices) << "run " << run;
    EXPECT_EQ(again.normals, first.normals) << "run " << run;
    EXPECT_EQ(again.faces, first.faces) << "run " << run;
  }
}

TEST(Pu, SphereFieldIsSignedAndAccurate) {
  auto f = Build(testing::SphereCloud(20000));
  ASSERT_TRUE(f);
  EXPECT_LT(testing::MaxSurfaceError(
                *f, [](const Vec3d& d) { return d; }, 500),
            2e-4);
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
    EXPECT_NEAR(core::EnclosedVolume(mesh), 4.0 / 3.0 * M_PI, 4 * M_PI * threshold * diagonal) << n;
  }
}

TEST(Pu, TorusMeshHasGenusOneAndLiesOnTheTorus) {
  const double R = 1.0, r = 0.35;
  auto f = Build(testing::TorusCloud(40000, R, r));
  ASSERT_TRUE(f);
  const core::TriangleMesh mesh = ExtractMesh(*f);
  const core::MeshTopology topo = core::AnalyzeTopology(mesh);
  EXPECT_TRUE(topo.watertight());
  EXPECT_EQ(topo.components, 1);
  EXPECT_EQ(topo.euler_characteristic(), 0);
  const testing::TorusField exact(R, r);
  double worst = 0;
  for (const auto& v : mesh.vertices) worst = std::max(worst, std::abs(exact.Distance(v.cast<double>())));
  EXPECT_LT(worst, 3e-3);  // Diagonal about 3.2; default threshold 3e-4 of it is 1e-3.
  EXPECT_NEAR(core::EnclosedVolume(mesh), 2 * M_PI * M_PI * R * r * r, 0.01 * 2 * M_PI * M_PI * R * r * r);
}

// A cube's surface with a square hole in two opposite faces: the data is open there, so the
// result must stay open and never reach far from the data.
core::PointCloud BoxWithHoles(size_t per_face) {
  core::PointCloud cloud;
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int axis = 0; axis < 3; ++axis) {
    for (int side : {-1, 1}) {
      for (size_t i = 0; i < per_face; ++i) {
        const double a = u(rng), b = u(rng);
        if (axis == 2 && std::abs(a) < 0.4 && std::abs(b) < 0.4) continue;  // The holes, on ±z.
        Vec3d p, n = Vec3d::Zero();
        p[axis] = side;
        p[(axis + 1) % 3] = a;
        p[(axis + 2) % 3] = b;
        n[axis] = side;
        cloud.positions.push_back(p.cast<float>());
        cloud.normals.push_back(n.cast<float>());
      }
    }
  }
  return cloud;
}

TEST(Pu, HolesInTheDataStayOpenAndNoSurfaceAppearsFarFromTheData) {
  const core::PointCloud cloud = BoxWithHoles(8000);
  auto f = Build(cloud);
  ASSERT_TRUE(f);
  const PuExtractParams extract;
  const core::TriangleMesh mesh = ExtractMesh(*f, extract);
  ASSERT_FALSE(mesh.faces.empty());
  const double cell = extract.cell_size * f->stats().mean_spacing * std::sqrt(2.0);  // Largest rounding.
  // Distance from every vertex to the nearest data point.
  const core::KdTree data(cloud.positions);
  double worst = 0;
  for (const auto& v : mesh.vertices) worst = std::max(worst, std::sqrt(double{data.Nearest(v).distance2}));
  EXPECT_LT(worst, 2 * cell);
  const core::MeshTopology topo = core::AnalyzeTopology(mesh);
  EXPECT_GT(topo.boundary_edges, 0);  // Both holes open.
  EXPECT_EQ(topo.non_manifold_edges, 0);
  // The hole centres are far from any surface.
  for (const auto& v : mesh.vertices) {
    EXPECT_FALSE(std::abs(v.z()) > 0.9 && std::abs(v.x()) < 0.2 && std::abs(v.y()) < 0.2) << v.transpose();
  }
}

TEST(Pu, DegreeStatisticsFollowTheThreshold) {
  // A torus is curved everywhere: a loose threshold accepts large quadratic cells, a tight one
  // needs smaller cells and higher degrees where the data is too sparse for planes.
  const core::PointCloud cloud = testing::TorusCloud(100000, 1.0, 0.35);
  PuParams fine, coarse;
  fine.error_threshold = 1e-4;
  coarse.error_threshold = 3e-3;
  auto f_fine = Build(cloud, fine);
  auto f_coarse = Build(cloud, coarse);
  ASSERT_TRUE(f_fine && f_coarse);
  auto total = [](const PuStats& s) {
    int64_t sum = s.quadric_fits;
    for (int64_t c : s.fits_per_degree) sum += c;
    return sum;
  };
  auto high_degree_share = [&](const PuStats& s) {
    return static_cast<double>(s.fits_per_degree[3] + s.fits_per_degree[4]) / static_cast<double>(total(s));
  };
  auto deepest = [](const PuStats& s) {
    int d = 0;
    for (size_t i = 0; i < s.fits_per_depth.size(); ++i) d = s.fits_per_depth[i] > 0 ? static_cast<int>(i) : d;
    return d;
  };
  const PuStats& a = f_fine->stats();
  const PuStats& b = f_coarse->stats();
  EXPECT_GT(total(a), 4 * total(b));
  EXPECT_GT(deepest(a), deepest(b));
  EXPECT_GT(high_degree_share(a), 2 * high_degree_share(b));
  // The loose threshold is met by quadratics almost everywhere.
  EXPECT_EQ(std::max_element(b.fits_per_degree.begin(), b.fits_per_degree.end()) - b.fits_per_degree.begin(), 2);
}

// Gaussian noise along the normal, σ = 0.3 % of the diagonal: the estimate finds σ, and the
// noise-aware bounds give one closed surface that averages the noise out. Declared exact, the
// same cloud is fitted down to its noise.
TEST(Pu, NoisySphereIsEstimatedAndSmoothedIntoOneClosedSurface) {
  const double diagonal = 2 * std::sqrt(3.0), sigma = 0.003 * diagonal;
  core::PointCloud cloud = testing::SphereCloud(30000);
  std::mt19937_64 rng(11);
  std::normal_distribution<double> noise(0.0, sigma);
  for (size_t i = 0; i < cloud.size(); ++i) {
    cloud.positions[i] += (noise(rng) * cloud.normals[i].cast<double>()).cast<float>();
  }
  auto clean = Build(testing::SphereCloud(30000));
  ASSERT_TRUE(clean);
  EXPECT_LT(clean->stats().noise_estimate, 1e-5);
  EXPECT_EQ(clean->stats().min_points, PuParams{}.min_points);  // Clean data keeps its bounds.

  auto f = Build(cloud);
  ASSERT_TRUE(f);
  EXPECT_NEAR(f->stats().noise_estimate, 0.003, 0.0006);
  EXPECT_NEAR(f->stats().error_threshold, 3 * f->stats().noise_estimate, 1e-12);
  const core::TriangleMesh mesh = ExtractMesh(*f);
  const core::MeshTopology topo = core::AnalyzeTopology(mesh);
  EXPECT_EQ(topo.boundary_edges, 0);
  EXPECT_EQ(topo.components, 1);
  EXPECT_EQ(topo.euler_characteristic(), 2);
  auto rms_deviation = [](const core::TriangleMesh& m) {
    double sum = 0;
    for (const auto& v : m.vertices) sum += std::pow(v.cast<double>().norm() - 1.0, 2);
    return std::sqrt(sum / static_cast<double>(m.vertices.size()));
  };
  const double smoothed = rms_deviation(mesh);
  EXPECT_LT(smoothed, 0.35 * sigma);

  PuParams exact;
  exact.noise_level = 0;
  auto g = Build(cloud, exact);
  ASSERT_TRUE(g);
  EXPECT_GT(rms_deviation(ExtractMesh(*g)), 1.5 * smoothed);
}

// An open sheet (a single view's surface) ends at the rim of its points: past the rim the points
// lie to one side, and F is defined only within a short reach of them. The full reach, kept where
// points surround a gap, ran the sheet on by more than three sample spacings all along its rim.
TEST(Pu, AnOpenSheetEndsAtTheRimOfItsPoints) {
  const double polar = 0.6, spacing = 0.0075;
  const core::PointCloud cloud = testing::CapCloud(polar, spacing);
  auto f = Build(cloud);
  ASSERT_TRUE(f);
  auto overshoot_of = [&](const core::TriangleMesh& m) {
    double most = -1;
    for (const core::Vec3f& v : m.vertices) {
      most = std::max(most, std::acos(std::clamp(v.cast<double>().normalized().z(), -1.0, 1.0)) - polar);
    }
    return most;
  };
  const core::TriangleMesh mesh = ExtractMesh(*f);
  ASSERT_FALSE(mesh.vertices.empty());
  EXPECT_LT(overshoot_of(mesh), 2 * spacing);  // 1.3 spacings here; 3.4 with the full reach.
  // And it still reaches the rim: every point there has the mesh within a spacing.
  const core::KdTree vertices(mesh.vertices);
  size_t rim = 0, reached = 0;
  for (const core::Vec3f& p : cloud.positions) {
    if (std::acos(static_cast<double>(p.z())) < polar - spacing) continue;
    ++rim;
    reached += vertices.Nearest(p).distance2 < spacing * spacing;
  }
  EXPECT_GT(rim, 100u);
  EXPECT_GT(static_cast<double>(reached), 0.98 * static_cast<double>(rim));
  const core::MeshTopology topo = core::AnalyzeTopology(mesh);
  EXPECT_EQ(topo.components, 1);
  EXPECT_EQ(topo.non_manifold_edges, 0);
  // A surface to be filled keeps the full reach.
  f->KeepFullReachPastRims();
  EXPECT_GT(overshoot_of(ExtractMesh(*f)), 3 * spacing);
}

TEST(Pu, ThinFingersStayClosed) {
  std::vector<testing::Capsule> fingers;
  const double spacing = 0.004;  // Fingers of radius 0.005 are 2.5 nearest-neighbour distances.
  const core::PointCloud cloud = testing::HandCloud(spacing, fingers);
  auto f = Build(cloud);
  ASSERT_TRUE(f);
  const core::TriangleMesh mesh = ExtractMesh(*f);
  // Closed and one genus-0 surface, also once welded by position (as STL export does).
  for (const core::TriangleMesh& m : {mesh, core::WeldByPosition(mesh)}) {
    const core::MeshTopology topo = core::AnalyzeTopology(m);
    EXPECT_TRUE(topo.watertight()) << topo.boundary_edges << " boundary, " << topo.non_manifold_edges
                                   << " non-manifold edges";
    EXPECT_EQ(topo.components, 1);
    EXPECT_EQ(topo.euler_characteristic(), 2);
  }
  // Every vertex near the true surface, and every finger tip reached.
  auto distance = [&](const Vec3d& x) {
    double d = x.norm() - 0.3;
    for (const testing::Capsule& c : fingers) d = std::min(d, c.Distance(x));
    return d;
  };
  double worst = 0;
  for (const auto& v : mesh.vertices) worst = std::max(worst, std::abs(distance(v.cast<double>())));
  // Measured 3.0e-3: the concave junctions are rounded and the thinnest finger bulges by 0.6 of
  // its radius where its two sides read as a crease (general quadric fallbacks: 6.3e-3 and open).
  EXPECT_LT(worst, spacing);
  for (const testing::Capsule& c : fingers) {
    float nearest = std::numeric_limits<float>::infinity();
    for (const auto& v : mesh.vertices) nearest = std::min(nearest, (v - c.b.cast<float>()).norm());
    EXPECT_NEAR(nearest, c.r, 0.25 * spacing) << "tip at " << c.b.transpose();
  }
}

TEST(Pu, RejectsBadInput) {
  core::LocalJobContext ctx;
  core::PointCloud bare = testing::SphereCloud(100);
  bare.normals.clear();
  EXPECT_EQ(BuildPu(bare, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  PuParams p;
  p.max_degree = 5;
  EXPECT_EQ(BuildPu(testing::SphereCloud(100), p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  p = {};
  p.error_threshold = 0;
  EXPECT_EQ(BuildPu(testing::SphereCloud(100), p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  p = {};
  p.noise_level = -0.5;
  EXPECT_EQ(BuildPu(testing::SphereCloud(100), p, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::pu
