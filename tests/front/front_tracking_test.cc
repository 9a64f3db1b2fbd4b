#include "worker/front/front_tracking.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <numbers>

#include "worker/core/mesh_metrics.h"

namespace lsqsurf::front {
namespace {

using core::Vec3d;

const double kSphereVolume = 4.0 / 3.0 * std::numbers::pi * 0.15 * 0.15 * 0.15;

Front Sphere(double h) {
  auto f = SampleInitialFront(InitialShape::kSphere, h);
  EXPECT_TRUE(f.ok()) << f.status();
  return f.ok() ? *std::move(f) : Front{};
}

// METHODS.md §2.4: all gridline intersections of a sphere of radius 0.15 at h = 1/256, thinned
// at h/2, leave about 17.4k points (the greedy order changes the count a little).
TEST(FrontTracking, SphereSamplingMatchesTheGridlineCount) {
  const Front front = Sphere(1.0 / 256);
  EXPECT_NEAR(static_cast<double>(front.points.size()), 17402, 0.05 * 17402);
  for (size_t i = 0; i < front.points.size(); ++i) {
    const Vec3d d = front.points[i].cast<double>() - Vec3d(0.35, 0.35, 0.35);
    EXPECT_NEAR(d.norm(), 0.15, 1e-6);
    EXPECT_NEAR(front.normals[i].cast<double>().dot(d.normalized()), 1.0, 1e-5);
  }
}

TEST(FrontTracking, VolumeAndShapeErrorOfTheExactSphere) {
  for (double h : {1.0 / 64, 1.0 / 128}) {
    const Front front = Sphere(h);
    auto v = FrontVolume(front, h);
    ASSERT_TRUE(v.ok()) << v.status();
    EXPECT_NEAR(*v / kSphereVolume, 1.0, 2e-3) << h;
    auto e1 = ShapeError(front, InitialShape::kSphere, h);
    ASSERT_TRUE(e1.ok()) << e1.status();
    EXPECT_LT(*e1 / kSphereVolume, 2e-3) << h;
    // Against a different shape the error is the volume of the difference.
    auto e1_slotted = ShapeError(front, InitialShape::kZalesakSphere, h);
    ASSERT_TRUE(e1_slotted.ok());
    EXPECT_GT(*e1_slotted / kSphereVolume, 1.5);  // Two disjoint balls, almost: ≈ 2 V.
  }
}

// The mesh of the front's surface encloses the same volume as the gridline measure, and both
// converge to the sphere's; the mesh is closed.
TEST(FrontTracking, MeshVolumeCrossChecksTheGridlineVolume) {
  double previous_error = 1;
  for (double h : {1.0 / 32, 1.0 / 64, 1.0 / 128}) {
    const Front front = Sphere(h);
    core::LocalJobContext ctx;
    auto mesh = FrontMesh(front, h, ctx);
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    EXPECT_TRUE(core::AnalyzeTopology(*mesh).watertight()) << h;
    const double mesh_volume = core::EnclosedVolume(*mesh);
    auto grid_volume = FrontVolume(front, h);
    ASSERT_TRUE(grid_volume.ok());
    const double error = std::abs(mesh_volume / kSphereVolume - 1);
    std::printf("h = 1/%.0f: mesh volume error %.3e, gridline volume error %.3e\n", 1 / h, error,
                std::abs(*grid_volume / kSphereVolume - 1));
    EXPECT_LT(error, 0.02) << h;
    EXPECT_LT(error, previous_error) << h;
    EXPECT_NEAR(mesh_volume / *grid_volume, 1.0, 0.02) << h;
    previous_error = error;
  }
}

// A constant velocity: the front moves rigidly; the volume stays within a bound that shrinks
// as h halves, and the points stay on the translated sphere.
TEST(FrontTracking, TranslationKeepsTheVolume) {
  std::vector<double> changes;
  for (double h : {1.0 / 32, 1.0 / 64}) {
    auto field = GridVelocity(Vec3d::Zero(), Vec3d::Constant(1.0), 1, 1, 1, {Vec3d(0.01, 0.006, -0.004)});
    ASSERT_TRUE(field.ok());
    TrackingParams p;
    p.h = h;
    p.dt = 1;
    p.steps = 20;
    p.output_stride = 20;
    double worst = 0;
    Front last;
    core::LocalJobContext ctx;
    ASSERT_TRUE(Track(Sphere(h), **field, p, ctx, [&](const FrameStats& s, const Front& f) {
                  worst = std::max(worst, std::abs(s.volume_change));
                  last = f;
                  return absl::OkStatus();
                }).ok());
    const Vec3d centre = Vec3d(0.35, 0.35, 0.35) + 20 * Vec3d(0.01, 0.006, -0.004);
    double deviation = 0;
    for (const auto& q : last.points) deviation = std::max(deviation, std::abs((q.cast<double>() - centre).norm() - 0.15));
    EXPECT_LT(deviation, 0.05 * h) << h;
    changes.push_back(worst);
  }
  EXPECT_LT(changes[0], 0.01);
  EXPECT_LT(changes[1], changes[0]) << changes[0] << " " << changes[1];
}

TEST(FrontTracking, RotationKeepsTheVolumeAndTheShape) {
  const double h = 1.0 / 64;
  const auto rotation = ZalesakRotation();
  TrackingParams p;
  p.h = h;
  p.dt = 2;
  p.steps = 50;  // A sixth of a revolution.
  p.output_stride = 10;
  int frames = 0;
  double worst = 0;
  core::LocalJobContext ctx;
  auto initial = SampleInitialFront(InitialShape::kSphere, h);
  ASSERT_TRUE(initial.ok());
  ASSERT_TRUE(Track(*initial, *rotation, p, ctx, [&](const FrameStats& s, const Front&) {
                ++frames;
                worst = std::max(worst, std::abs(s.volume_change));
                EXPECT_GT(s.points, initial->points.size() * 9 / 10);
                return absl::OkStatus();
              }).ok());
  EXPECT_EQ(frames, 6);  // Step 0 and every 10th.
  EXPECT_LT(worst, 0.01);
}

class NanField final : public VelocityField {
 public:
  Vec3d At(const Vec3d& x, double) const override {
    return x.x() > 0.4 ? Vec3d(std::numeric_limits<double>::quiet_NaN(), 0, 0) : Vec3d::Zero();
  }
};

TEST(FrontTracking, RejectsBadFieldsAndParameters) {
  EXPECT_EQ(GridVelocity(Vec3d::Zero(), Vec3d::Constant(0.1), 2, 1, 1, {Vec3d::Zero(), Vec3d(NAN, 0, 0)}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(GridVelocity(Vec3d::Zero(), Vec3d::Constant(0.1), 2, 2, 1, {Vec3d::Zero()}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(GridVelocity(Vec3d::Zero(), Vec3d(0.1, 0.0, 0.1), 1, 1, 1, {Vec3d::Zero()}).status().code(),
            absl::StatusCode::kInvalidArgument);
  const Front front = Sphere(1.0 / 32);
  core::LocalJobContext ctx;
  auto ignore = [](const FrameStats&, const Front&) { return absl::OkStatus(); };
  TrackingParams p;
  p.h = 1.0 / 32;
  const NanField nan_field;
  const absl::Status nan = Track(front, nan_field, p, ctx, ignore);
  EXPECT_EQ(nan.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(nan.message().find("non-finite"), std::string::npos) << nan;
  const auto rotation = ZalesakRotation();
  p.dt = 0;
  EXPECT_EQ(Track(front, *rotation, p, ctx, ignore).code(), absl::StatusCode::kInvalidArgument);
  p = {};
  p.h = 1.0 / 1024;  // Finer than the grid limits.
  EXPECT_EQ(Track(front, *rotation, p, ctx, ignore).code(), absl::StatusCode::kInvalidArgument);
  p.h = 0.3;  // Does not divide the unit cube.
  EXPECT_EQ(Track(front, *rotation, p, ctx, ignore).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(Track(Front{}, *rotation, TrackingParams{}, ctx, ignore).code(), absl::StatusCode::kInvalidArgument);
  p = {};
  p.h = 1.0 / 32;
  p.max_points = 50;  // Fewer than the sphere needs.
  EXPECT_EQ(Track(front, *rotation, p, ctx, ignore).code(), absl::StatusCode::kResourceExhausted);
}

}  // namespace
}  // namespace lsqsurf::front
