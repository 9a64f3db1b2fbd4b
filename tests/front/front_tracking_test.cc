#include "worker/front/front_tracking.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <numbers>

#include "worker/core/kd_tree.h"
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

class Resamplings : public ::testing::TestWithParam<Resampling> {};

// A constant velocity: the front moves rigidly; the volume stays within a bound that shrinks
// as h halves, and the points stay on the translated sphere.
TEST_P(Resamplings, TranslationKeepsTheVolume) {
  std::vector<double> changes;
  for (double h : {1.0 / 32, 1.0 / 64}) {
    auto field = GridVelocity(Vec3d::Zero(), Vec3d::Constant(1.0), 1, 1, 1, {Vec3d(0.01, 0.006, -0.004)});
    ASSERT_TRUE(field.ok());
    TrackingParams p;
    p.resampling = GetParam();
    p.regeneration_stretch = 1;  // A translation never stretches: re-generate every step anyway.
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
    for (const auto& q : last.points)
      deviation = std::max(deviation, std::abs((q.cast<double>() - centre).norm() - 0.15));
    EXPECT_LT(deviation, 0.05 * h) << h;
    changes.push_back(worst);
  }
  EXPECT_LT(changes[0], 0.01);
  EXPECT_LT(changes[1], changes[0]) << changes[0] << " " << changes[1];
}

TEST_P(Resamplings, RotationKeepsTheVolumeAndTheShape) {
  const double h = 1.0 / 64;
  const auto rotation = ZalesakRotation();
  TrackingParams p;
  p.resampling = GetParam();
  p.regeneration_stretch = 1;  // A rotation never stretches: re-generate every step anyway.
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

INSTANTIATE_TEST_SUITE_P(FrontTracking, Resamplings, ::testing::Values(Resampling::kMarkers, Resampling::kGridlines),
                         [](const ::testing::TestParamInfo<Resampling>& p) {
                           return p.param == Resampling::kMarkers ? "Markers" : "Gridlines";
                         });

// v = rate (x − c): a sphere about c stays a sphere of radius r₀ e^{rate t}, its normals stay
// radial, and its volume is V₀ e^{3 rate t} exactly.
class RadialField final : public VelocityField {
 public:
  explicit RadialField(double rate) : rate_(rate) {}
  Vec3d At(const Vec3d& x, double) const override { return rate_ * (x - Vec3d(0.35, 0.35, 0.35)); }

 private:
  double rate_;
};

// Markers: an expanding sphere gets new points where the old ones part, a shrinking one loses
// the crowded ones; the points stay on the exact sphere, the volume follows e^{3 rate t}, and
// the spacing rules hold (no two points facing the same way within h/2; every point of the
// sphere has a marker within h).
TEST(FrontTracking, MarkersFollowAnExpandingAndAShrinkingSphere) {
  const double h = 1.0 / 64;
  for (double rate : {0.5, -0.5}) {
    const RadialField field(rate);
    TrackingParams p;
    p.h = h;
    p.dt = 0.02;
    p.steps = 50;  // t = 1: the radius grows to 0.247 or shrinks to 0.091.
    p.output_stride = 50;
    const Front start = Sphere(h);
    Front last;
    double change = 0;
    core::LocalJobContext ctx;
    ASSERT_TRUE(Track(start, field, p, ctx, [&](const FrameStats& s, const Front& f) {
                  last = f;
                  change = s.volume_change;
                  return absl::OkStatus();
                }).ok());
    const double radius = 0.15 * std::exp(rate);
    EXPECT_NEAR(change, std::expm1(3 * rate), 5e-3 * std::exp(3 * rate)) << rate;
    double deviation = 0, normal_error = 0;
    for (size_t i = 0; i < last.points.size(); ++i) {
      const Vec3d d = last.points[i].cast<double>() - Vec3d(0.35, 0.35, 0.35);
      deviation = std::max(deviation, std::abs(d.norm() - radius));
      normal_error = std::max(normal_error, 1 - last.normals[i].cast<double>().dot(d.normalized()));
    }
    EXPECT_LT(deviation, 1e-5) << rate;
    EXPECT_LT(normal_error, 1e-5) << rate;
    // New points where it grew, fewer where it shrank; and the count lies between the covering
    // bound (discs of radius h around the points cover the sphere) and the packing bound (no two
    // points within h/2).
    if (rate > 0) {
      EXPECT_GT(last.points.size(), start.points.size());
    } else {
      EXPECT_LT(last.points.size(), start.points.size());
    }
    const double area = 4 * std::numbers::pi * radius * radius;
    const auto count = static_cast<double>(last.points.size());
    EXPECT_GT(count, area / (std::numbers::pi * h * h)) << rate;
    EXPECT_LT(count, area / (std::sqrt(3.0) / 2 * 0.25 * h * h)) << rate;
    const core::KdTree tree(last.points);
    for (const auto& q : last.points) {
      std::vector<core::Neighbor> two;
      tree.Knn(q, 2, two);
      ASSERT_EQ(two.size(), 2u);
      EXPECT_GE(std::sqrt(two[1].distance2), 0.5 * h * (1 - 1e-5)) << rate;
    }
    // Probe the sphere on a Fibonacci spiral for holes.
    double widest = 0;
    for (int k = 0; k < 2000; ++k) {
      const double z = 1 - (2 * k + 1) / 2000.0, r = std::sqrt(1 - z * z), phi = 2.399963229728653 * k;
      const Vec3d probe = Vec3d(0.35, 0.35, 0.35) + radius * Vec3d(r * std::cos(phi), r * std::sin(phi), z);
      widest = std::max(widest, std::sqrt(static_cast<double>(tree.Nearest(probe.cast<float>()).distance2)));
    }
    EXPECT_LT(widest, h) << rate;
  }
}

// Enright's deformation stretches the sphere into a sheet far thinner than h and brings it back
// at t = T. Markers keep the sheet, so the sphere returns (the gridline re-generation loses the
// sheet and returns with E1/V0 above 100 % here; worker/front/README.md).
TEST(FrontTracking, MarkersBringTheSphereBackFromEnrightsDeformation) {
  const double h = 1.0 / 32;
  const auto field = EnrightDeformation(3.0);
  TrackingParams p;
  p.h = h;
  p.steps = 75;
  p.dt = 3.0 / p.steps;
  p.output_stride = p.steps;
  Front last;
  double change = 0;
  core::LocalJobContext ctx;
  ASSERT_TRUE(Track(Sphere(h), *field, p, ctx, [&](const FrameStats& s, const Front& f) {
                last = f;
                change = s.volume_change;
                return absl::OkStatus();
              }).ok());
  auto e1 = ShapeError(last, InitialShape::kSphere, h);
  ASSERT_TRUE(e1.ok()) << e1.status();
  std::printf("h = 1/32: volume change %.3f %%, E1/V0 %.2f %%, %zu points\n", 100 * change, 100 * *e1 / kSphereVolume,
              last.points.size());
  EXPECT_LT(std::abs(change), 0.01);
  EXPECT_LT(*e1 / kSphereVolume, 0.12);
}

// The seed's deformation test (T = 2, the field reversed at T/2) at h = 1/128 in the gridline
// mode. Re-generating every step, the fitting errors added while the sphere is stretched thinnest
// are amplified by the returning flow and the front grows without bound (+10 % volume and E1/V0
// 120 % at t = 2 here). Re-generating only once the flow may have spread the points by
// regeneration_stretch (1.5, the default) brings the sphere back with its volume.
TEST(FrontTracking, GridlinesHoldTheSeedsReversedDeformation) {
  const auto field = EnrightDeformation(2.0, TimeModulation::kReversal);
  TrackingParams p;
  p.resampling = Resampling::kGridlines;
  p.h = 1.0 / 128;
  p.steps = 157;
  p.dt = 2.0 / p.steps;
  p.output_stride = 10;
  struct Run {
    double worst_change = 0;
    Front last;
  };
  auto run = [&](const TrackingParams& params) {
    Run r;
    core::LocalJobContext ctx;
    EXPECT_TRUE(Track(Sphere(p.h), *field, params, ctx, [&](const FrameStats& s, const Front& f) {
                  r.worst_change = std::max(r.worst_change, std::abs(s.volume_change));
                  r.last = f;
                  return absl::OkStatus();
                }).ok());
    return r;
  };
  const Run held = run(p);
  auto e1 = ShapeError(held.last, InitialShape::kSphere, p.h);
  ASSERT_TRUE(e1.ok()) << e1.status();
  std::printf("stretch 1.5: largest volume change %.3f %%, E1/V0 %.2f %%, %zu points at t = 2\n",
              100 * held.worst_change, 100 * *e1 / kSphereVolume, held.last.points.size());
  EXPECT_LT(held.worst_change, 0.015);
  EXPECT_LT(*e1 / kSphereVolume, 0.12);
  const size_t start = Sphere(p.h).points.size();
  EXPECT_LT(std::abs(static_cast<double>(held.last.points.size()) / static_cast<double>(start) - 1), 0.15);
}

class NanField final : public VelocityField {
 public:
  Vec3d At(const Vec3d& x, double) const override {
    return x.x() > 0.4 ? Vec3d(std::numeric_limits<double>::quiet_NaN(), 0, 0) : Vec3d::Zero();
  }
};

// The reversed field is the cosine field's sign at full speed, and RK4 through it brings points
// back to where they started; when T/2 falls in the middle of a step (the seed's 625 steps of
// 0.0032) exactly: the zero at T/2 lets that step's two halves cancel as the exact flow does.
TEST(FrontTracking, TheReversedDeformationFieldReturnsEveryPoint) {
  const auto reversal = EnrightDeformation(2.0, TimeModulation::kReversal);
  const auto cosine = EnrightDeformation(2.0);
  const Vec3d p(0.31, 0.42, 0.27);
  for (double t : {0.1, 0.7, 1.3, 1.9}) {
    const Vec3d r = reversal->At(p, t), c = cosine->At(p, t);
    EXPECT_NEAR(r.dot(c), r.norm() * c.norm(), 1e-12) << t;                                      // The same direction,
    EXPECT_NEAR(r.norm(), c.norm() / std::abs(std::cos(std::numbers::pi * t / 2)), 1e-12) << t;  // at full speed.
  }
  EXPECT_EQ(reversal->At(p, 1.0).norm(), 0.0);
  for (int steps : {625, 400}) {  // T/2 mid-step, and on a step boundary.
    const double dt = 2.0 / steps;
    double largest = 0, moved = 0;
    for (const Vec3d& start : {Vec3d(0.35, 0.5, 0.35), Vec3d(0.3, 0.3, 0.45), Vec3d(0.5, 0.2, 0.3)}) {
      Vec3d x = start;
      for (int k = 0; k < steps; ++k) {
        x = Rk4Step(*reversal, x, k * dt, dt);
        if (k == steps / 2) moved = std::max(moved, (x - start).norm());
      }
      largest = std::max(largest, (x - start).norm());
    }
    EXPECT_GT(moved, 0.05) << steps;  // They did travel.
    // Mid-step the two halves cancel exactly; on a boundary the steps on either side see the zero
    // in place of their one-sided limit, an error of a sixth of a step's speed each.
    EXPECT_LT(largest, steps == 625 ? 1e-6 : 1e-4) << steps;
  }
}

TEST(FrontTracking, RejectsBadFieldsAndParameters) {
  EXPECT_EQ(
      GridVelocity(Vec3d::Zero(), Vec3d::Constant(0.1), 2, 1, 1, {Vec3d::Zero(), Vec3d(NAN, 0, 0)}).status().code(),
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
  p.max_points = 100;  // Fewer than the sphere needs.
  EXPECT_EQ(Track(front, *rotation, p, ctx, ignore).code(), absl::StatusCode::kResourceExhausted);
  p = {};
  p.h = 1.0 / 32;
  p.marker_gap = 0.4;  // Not above marker_spacing: gaps would be filled and thinned again at once.
  const absl::Status gap = Track(front, *rotation, p, ctx, ignore);
  EXPECT_EQ(gap.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(gap.message().find("marker_gap"), std::string::npos) << gap;
  p = {};
  p.h = 1.0 / 32;
  p.merge_distance = 1.6;  // A blend wider than the support (3h) would see only one side.
  const absl::Status merge = Track(front, *rotation, p, ctx, ignore);
  EXPECT_EQ(merge.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(merge.message().find("merge_distance"), std::string::npos) << merge;
  p = {};
  p.h = 1.0 / 32;
  p.regeneration_stretch = 0.5;  // Points cannot have come closer by stretching.
  const absl::Status stretch = Track(front, *rotation, p, ctx, ignore);
  EXPECT_EQ(stretch.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(stretch.message().find("regeneration_stretch"), std::string::npos) << stretch;
}

}  // namespace
}  // namespace lsqsurf::front
