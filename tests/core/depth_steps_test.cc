#include "worker/core/depth_steps.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <optional>

#include "tests/test_shapes.h"
#include "worker/core/normals.h"

namespace lsqsurf::core {
namespace {

const Vec3d kEye(0, -2.5, 1.6);

// Root mean square distance of the points to the true surface of BallOnATableView (the ball of
// radius 0.3 about (0, 0, 0.3) or the table z = 0, whichever is nearer).
double DistanceToTruth(std::span<const Vec3f> points) {
  double sum = 0;
  for (const Vec3f& p : points) {
    const Vec3d q = p.cast<double>();
    const double d = std::min(std::abs((q - Vec3d(0, 0, 0.3)).norm() - 0.3), std::abs(q.z()));
    sum += d * d;
  }
  return std::sqrt(sum / static_cast<double>(points.size()));
}

// Share of the estimated normals (turned toward the eye) within 15° of the true ones.
double NormalsWithin15Degrees(std::span<const Vec3f> points, std::span<const Vec3f> truth) {
  LocalJobContext ctx;
  NormalEstimationParams params;
  params.viewpoints = {kEye};
  auto normals = EstimateNormals(points, params, ctx);
  EXPECT_TRUE(normals.ok()) << normals.status();
  if (!normals.ok()) return 0;
  size_t good = 0;
  for (size_t i = 0; i < truth.size(); ++i) good += (*normals)[i].dot(truth[i]) >= std::cos(15 * M_PI / 180);
  return static_cast<double>(good) / static_cast<double>(truth.size());
}

struct Undone {
  DepthStepResult result;
  std::vector<Vec3f> points;
};

void Print(const DepthStepResult& r, size_t points) {
  std::printf("  exact %.3f, family %.3f, levels %zu, step %.4f (agreement %.2f), moved %zu of %zu\n", r.exact_share,
              r.family_share, r.levels, r.step, r.step_agreement, r.moved, points);
}

Undone Undo(std::vector<Vec3f> points, const std::optional<Vec3d>& eye) {
  LocalJobContext ctx;
  auto result = UndoDepthSteps(points, eye, {}, ctx);
  EXPECT_TRUE(result.ok()) << result.status();
  return {result.ok() ? *result : DepthStepResult{}, std::move(points)};
}

// A stereo-like view whose depths take only the values 1 / (k Δ), each terrace of the table many
// pixels deep: the steps are found, every point moves by at most half a step along its own ray,
// the points come nearer the true surface, and normals estimated from them follow the surface
// instead of the optical axis.
TEST(DepthSteps, DisparityStepsAreUndone) {
  const PointCloud view = testing::BallOnATableView(kEye, {.scale = 4, .step = 0.012});
  const Undone undone = Undo(view.positions, kEye);
  Print(undone.result, view.size());
  ASSERT_TRUE(undone.result.found);
  EXPECT_FALSE(undone.result.radial);
  EXPECT_GT(undone.result.moved, view.size() / 2);
  for (size_t i = 0; i < view.size(); ++i) {
    const Vec3d before = view.positions[i].cast<double>() - kEye, after = undone.points[i].cast<double>() - kEye;
    ASSERT_GT(before.normalized().dot(after.normalized()), 1 - 1e-9) << "point " << i << " left its ray";
  }
  const double stepped = DistanceToTruth(view.positions), smoothed = DistanceToTruth(undone.points);
  const double normals_stepped = NormalsWithin15Degrees(view.positions, view.normals);
  const double normals_smoothed = NormalsWithin15Degrees(undone.points, view.normals);
  std::printf("  distance to the truth %.3e -> %.3e; normals within 15 degrees %.3f -> %.3f\n", stepped, smoothed,
              normals_stepped, normals_smoothed);
  EXPECT_LT(smoothed, 0.5 * stepped);
  EXPECT_GT(normals_smoothed, 0.9);
  EXPECT_LT(normals_stepped, 0.7);
}

// A time-of-flight camera's steps lie on spheres about the eye, not on planes square to its axis.
TEST(DepthSteps, RangeStepsAreUndone) {
  const PointCloud view = testing::BallOnATableView(kEye, {.scale = 4, .step = 0.05, .range_steps = true});
  const Undone undone = Undo(view.positions, kEye);
  Print(undone.result, view.size());
  ASSERT_TRUE(undone.result.found);
  EXPECT_TRUE(undone.result.radial);
  EXPECT_NEAR(undone.result.step, 0.05, 0.005);
  const double stepped = DistanceToTruth(view.positions), smoothed = DistanceToTruth(undone.points);
  std::printf("  distance to the truth %.3e -> %.3e\n", stepped, smoothed);
  EXPECT_LT(smoothed, 0.5 * stepped);
}

// Without the sensor's position, a view in its sensor's own frame (as a camera's export writes
// it) is found by its disparity steps, which fit a sensor at the origin; the same view placed
// elsewhere, and range steps (which fit a sensor anywhere along the axis), are left alone.
TEST(DepthSteps, ASensorAtTheOriginIsFoundByItsSteps) {
  PointCloud view = testing::BallOnATableView(kEye, {.scale = 4, .step = 0.012});
  const Undone elsewhere = Undo(view.positions, std::nullopt);
  EXPECT_FALSE(elsewhere.result.found);
  EXPECT_EQ(elsewhere.points, view.positions);
  for (Vec3f& p : view.positions) p -= kEye.cast<float>();
  const Undone undone = Undo(view.positions, std::nullopt);
  ASSERT_TRUE(undone.result.found);
  EXPECT_TRUE(undone.result.eye_inferred);
  EXPECT_GT(undone.result.moved, view.size() / 2);
  PointCloud ranged = testing::BallOnATableView(kEye, {.scale = 4, .step = 0.05, .range_steps = true});
  for (Vec3f& p : ranged.positions) p -= kEye.cast<float>();
  EXPECT_FALSE(Undo(ranged.positions, std::nullopt).result.found);
}

// Clouds without steps keep every point where it is: the same view unquantized, a sampled
// sphere, and a CAD part whose flat faces point many ways, each seen from an eye outside it.
TEST(DepthSteps, CloudsWithoutStepsStayAsTheyAre) {
  const PointCloud view = testing::BallOnATableView(kEye);
  const PointCloud sphere = testing::SphereCloud(20000);
  const PointCloud block = testing::DrilledBlockCloud(40000);
  for (const auto& [cloud, eye] :
       {std::pair{&view, kEye}, std::pair{&sphere, Vec3d(0, 0, 4)}, std::pair{&block, Vec3d(2.5, 1.5, 3)}}) {
    const Undone undone = Undo(cloud->positions, eye);
    std::printf("  exact %.3f, family %.3f, levels %zu\n", undone.result.exact_share, undone.result.family_share,
                undone.result.levels);
    EXPECT_FALSE(undone.result.found);
    EXPECT_EQ(undone.points, cloud->positions);
  }
}

// Flat faces square to the view at depths a sensor's steps do not explain (a shelf seen head-on,
// ten boards at unrelated depths): exactly flat, one family, ten levels, and still not steps.
TEST(DepthSteps, FacesAtUnrelatedDepthsAreNotSteps) {
  const double depths[] = {2.0, 2.13, 2.41, 2.47, 2.9, 3.05, 3.6, 3.71, 4.2, 4.55};
  std::vector<Vec3f> points;
  for (int row = 0; row < 240; ++row) {
    for (int column = 0; column < 320; ++column) {
      const Vec3d ray((column + 0.5) / 160.0 - 1, 0.75 * ((row + 0.5) / 120.0 - 1), 1.0);
      points.push_back((ray * depths[column / 32]).cast<float>());
    }
  }
  const Undone undone = Undo(points, Vec3d::Zero());
  std::printf("  exact %.3f, family %.3f, levels %zu, agreement %.2f\n", undone.result.exact_share,
              undone.result.family_share, undone.result.levels, undone.result.step_agreement);
  EXPECT_GE(undone.result.levels, 8u);
  EXPECT_FALSE(undone.result.found);
  EXPECT_EQ(undone.points, points);
}

TEST(DepthSteps, BadParametersAreRefused) {
  std::vector<Vec3f> points = testing::SphereCloud(1000).positions;
  LocalJobContext ctx;
  DepthStepParams params;
  params.window = 2;
  EXPECT_EQ(UndoDepthSteps(points, kEye, params, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(UndoDepthSteps(points, Vec3d(NAN, 0, 0), {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::core
