// Walls and gaps thinner than a leaf: a plate a third of a leaf thick, turned off the axes, comes
// out of the J1a extractor with holes through it from its exact distance field; with the probes
// of thin_walls.h its leaves are split where the lattice misses it, and it comes out one closed
// surface with a sphere's topology.
#include "worker/extract/thin_walls.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"

namespace lsqsurf::extract {
namespace {

using core::Vec3d;

// A box of half sides `half`, turned: max_k (|y_k| − half_k) in its own frame, exact on and
// inside its faces.
class TurnedBox final : public core::ImplicitFunction {
 public:
  explicit TurnedBox(const Vec3d& half)
      : half_(half), rotation_(Eigen::AngleAxisd(0.61, Vec3d(3, -1, 2).normalized()).toRotationMatrix()) {}

  core::FieldValue Value(const Vec3d& x) const override { return {Evaluate(x, nullptr), true}; }
  core::FieldGradient ValueAndGradient(const Vec3d& x) const override {
    Vec3d g;
    const double v = Evaluate(x, &g);
    return {v, g, true};
  }
  // Points spread evenly over the faces, with the faces' normals.
  core::PointCloud Sample(size_t count) const {
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> unit(-1, 1), share(0, 1);
    const Vec3d areas(half_.y() * half_.z(), half_.x() * half_.z(), half_.x() * half_.y());
    core::PointCloud cloud;
    while (cloud.positions.size() < count) {
      const double pick = share(rng) * areas.sum();
      const int axis = pick < areas.x() ? 0 : (pick < areas.x() + areas.y() ? 1 : 2);
      Vec3d y(unit(rng) * half_.x(), unit(rng) * half_.y(), unit(rng) * half_.z());
      Vec3d n = Vec3d::Zero();
      n[axis] = share(rng) < 0.5 ? -1 : 1;
      y[axis] = n[axis] * half_[axis];
      cloud.positions.push_back((rotation_ * y).cast<float>());
      cloud.normals.push_back((rotation_ * n).cast<float>());
    }
    return cloud;
  }
  // The box's own frame (its third axis is the plate's normal).
  Vec3d Local(const Vec3d& x) const { return rotation_.transpose() * x; }

 private:
  double Evaluate(const Vec3d& x, Vec3d* gradient) const {
    const Vec3d y = Local(x);
    int axis = 0;
    const Eigen::Array3d out = y.cwiseAbs().array() - half_.array();
    const double value = out.maxCoeff(&axis);
    if (gradient != nullptr) {
      Vec3d g = Vec3d::Zero();
      g[axis] = y[axis] < 0 ? -1 : 1;
      *gradient = rotation_ * g;
    }
    return value;
  }

  Vec3d half_;
  Eigen::Matrix3d rotation_;
};

constexpr double kLeaf = 0.012;
const Vec3d kPlateHalf(0.1, 0.075, 0.002);  // A third of a leaf thick.

TEST(ThinWallProbes, APlatesFacesGiveProbesInItsMiddleANoisyPlateAndASphereNone) {
  const TurnedBox plate(kPlateHalf);
  const core::PointCloud cloud = plate.Sample(8000);
  core::LocalJobContext ctx;
  auto probes = ThinWallProbes(cloud.positions, cloud.normals, kLeaf, {}, ctx);
  ASSERT_TRUE(probes.ok()) << probes.status();
  // The faces hold 97 % of the points; those within reach of the far face give probes.
  EXPECT_GT(probes->size(), cloud.positions.size() * 8 / 10);
  for (const SideProbe& probe : *probes) {
    ASSERT_TRUE(probe.inside);  // A wall, not a gap.
    EXPECT_LT(std::abs(plate.Local(probe.point.cast<double>()).z()), 0.05 * kPlateHalf.z());
    EXPECT_GT(std::abs(plate.Local(probe.normal.cast<double>()).z()), 0.999);
  }
  // Noise half the plate's thickness along the normals spreads the far face's offsets over about
  // a thickness: no probes there (the lattice could not follow such a wall).
  core::PointCloud noisy = cloud;
  std::mt19937_64 rng(11);
  std::normal_distribution<float> noise(0, static_cast<float>(kPlateHalf.z()));
  for (size_t i = 0; i < noisy.positions.size(); ++i) noisy.positions[i] += noise(rng) * noisy.normals[i];
  auto noisy_probes = ThinWallProbes(noisy.positions, noisy.normals, kLeaf, {}, ctx);
  ASSERT_TRUE(noisy_probes.ok()) << noisy_probes.status();
  EXPECT_LT(noisy_probes->size(), cloud.positions.size() / 20);
  // A cloud that is mostly such walls takes the wider spread: most points give probes, and the
  // medians of both faces put them nearer the middle than halfway from the point alone would be
  // (each point is off by σ, half the thickness: σ/2 RMS halfway; 0.26 σ measured).
  ThinWallParams wide;
  wide.max_spread = kNoisyWallSpread;
  auto wide_probes = ThinWallProbes(noisy.positions, noisy.normals, kLeaf, wide, ctx);
  ASSERT_TRUE(wide_probes.ok()) << wide_probes.status();
  EXPECT_GT(wide_probes->size(), cloud.positions.size() / 2);
  double squares = 0;
  for (const SideProbe& probe : *wide_probes) {
    EXPECT_TRUE(probe.inside);
    squares += std::pow(plate.Local(probe.point.cast<double>()).z(), 2);
  }
  EXPECT_LT(std::sqrt(squares / static_cast<double>(wide_probes->size())), 0.35 * kPlateHalf.z());
  // A sphere far thicker than a leaf has no point facing against another within reach.
  const core::PointCloud sphere = testing::SphereCloud(8000);
  auto none = ThinWallProbes(sphere.positions, sphere.normals, 0.1, {}, ctx);
  ASSERT_TRUE(none.ok()) << none.status();
  EXPECT_TRUE(none->empty());
}

core::MeshTopology PlateTopology(int probe_levels, int64_t* splits = nullptr) {
  const TurnedBox plate(kPlateHalf);
  const core::PointCloud cloud = plate.Sample(8000);
  core::LocalJobContext ctx;
  auto probes = ThinWallProbes(cloud.positions, cloud.normals, kLeaf, {}, ctx);
  EXPECT_TRUE(probes.ok()) << probes.status();
  J1aIsosurfaceParams params;
  params.cell_size = kLeaf;
  if (probe_levels > 0 && probes.ok()) params.probes = *probes;
  params.probe_levels = probe_levels;
  auto surface = ExtractIsosurfaceJ1a(plate, cloud.positions, params, ctx);
  EXPECT_TRUE(surface.ok()) << surface.status();
  if (!surface.ok()) return {};
  if (splits != nullptr) *splits = surface->stats.wall_splits;
  return core::AnalyzeTopology(core::WeldByPosition(surface->mesh));
}

TEST(ThinWallProbes, ThePlateComesOutClosedWithTheLeavesSplitWhereTheLatticeMissesIt) {
  const core::MeshTopology missed = PlateTopology(0);
  // Without the probes the lattice misses the plate in places: holes through it.
  EXPECT_TRUE(missed.components != 1 || missed.euler_characteristic() != 2 || missed.boundary_edges > 0)
      << missed.components << " components, Euler characteristic " << missed.euler_characteristic();
  int64_t splits = 0;
  const core::MeshTopology closed = PlateTopology(2, &splits);
  EXPECT_GT(splits, 0);
  EXPECT_EQ(closed.components, 1);
  EXPECT_EQ(closed.boundary_edges, 0);
  EXPECT_EQ(closed.non_manifold_edges, 0);
  EXPECT_EQ(closed.euler_characteristic(), 2);
}

TEST(ThinWallProbes, RefusesPointsWithoutNormals) {
  const std::vector<core::Vec3f> points(10, core::Vec3f::Zero());
  core::LocalJobContext ctx;
  EXPECT_EQ(ThinWallProbes(points, {}, kLeaf, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  J1aIsosurfaceParams params;
  params.cell_size = kLeaf;
  params.probe_levels = kMaxProbeLevels + 1;
  const TurnedBox plate(kPlateHalf);
  EXPECT_EQ(ExtractIsosurfaceJ1a(plate, points, params, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::extract
