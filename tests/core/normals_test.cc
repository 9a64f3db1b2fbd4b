#include "worker/core/normals.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/sampling.h"

namespace lsqsurf::core {
namespace {

struct AngleReport {
  double mean_degrees = 0;
  int flipped = 0;
};

AngleReport Compare(const std::vector<Vec3f>& estimated, const std::vector<Vec3f>& truth) {
  AngleReport r;
  for (size_t i = 0; i < truth.size(); ++i) {
    const double c = std::clamp<double>(estimated[i].dot(truth[i]), -1.0, 1.0);
    if (c < 0) ++r.flipped;
    r.mean_degrees += std::acos(std::abs(c)) * 180.0 / std::numbers::pi;
  }
  r.mean_degrees /= static_cast<double>(truth.size());
  return r;
}

// Normals of plain PCA (one neighbourhood size) and with the size chosen per point.
std::pair<AngleReport, AngleReport> OneSizeAndChosen(const PointCloud& cloud) {
  LocalJobContext ctx;
  NormalEstimationParams one_size;
  one_size.scales = 1;
  auto plain = EstimateNormals(cloud.positions, one_size, ctx);
  auto chosen = EstimateNormals(cloud.positions, {}, ctx);
  EXPECT_TRUE(plain.ok() && chosen.ok());
  if (!plain.ok() || !chosen.ok()) return {};
  return {Compare(*plain, cloud.normals), Compare(*chosen, cloud.normals)};
}

TEST(Normals, SphereIsAccurateAndOutward) {
  const PointCloud cloud = testing::SphereCloud(6000);
  LocalJobContext ctx;
  auto normals = EstimateNormals(cloud.positions, {}, ctx);
  ASSERT_TRUE(normals.ok()) << normals.status();
  const AngleReport r = Compare(*normals, cloud.normals);
  EXPECT_EQ(r.flipped, 0);
  EXPECT_LT(r.mean_degrees, 1.0);
}

TEST(Normals, TorusIsAccurateAndOutward) {
  const PointCloud cloud = testing::TorusCloud(20000, 1.0, 0.35);
  LocalJobContext ctx;
  auto normals = EstimateNormals(cloud.positions, {}, ctx);
  ASSERT_TRUE(normals.ok()) << normals.status();
  const AngleReport r = Compare(*normals, cloud.normals);
  EXPECT_EQ(r.flipped, 0);
  EXPECT_LT(r.mean_degrees, 2.0);
}

// A thin ring at scanner noise: the tube's radius is 1 % of the diagonal and the noise 0.1 % of
// it, about half the spacing of the points. The 12 nearest points see mostly noise; larger
// neighbourhoods flatten it out, and are chosen only where they are flatter.
TEST(Normals, NoisyThinRingTakesLargerNeighbourhoods) {
  const double R = 1.0, r = 0.03, diagonal = 2.0 * std::sqrt(2.0) * (R + r), sigma = 1e-3 * diagonal;
  PointCloud cloud = testing::TorusCloud(60000, R, r);
  std::mt19937_64 rng(17);
  std::normal_distribution<float> noise(0.0f, static_cast<float>(sigma));
  for (size_t i = 0; i < cloud.size(); ++i) cloud.positions[i] += noise(rng) * cloud.normals[i];
  const auto [before, after] = OneSizeAndChosen(cloud);
  EXPECT_LT(after.flipped, static_cast<int>(cloud.size() / 500)) << "plain PCA: " << before.flipped;
  EXPECT_LT(after.mean_degrees, 0.6 * before.mean_degrees);
}

TEST(Normals, SharpCreasesKeepTheSmallNeighbourhood) {
  // Across a block's 90° edges a larger neighbourhood would average the two faces.
  const PointCloud cloud = testing::DrilledBlockCloud(40000);
  const auto [before, after] = OneSizeAndChosen(cloud);
  EXPECT_EQ(after.flipped, 0);
  EXPECT_LE(after.mean_degrees, 1.05 * before.mean_degrees);
}

TEST(Normals, TwoSeparateSpheresAreBothOutward) {
  PointCloud a = testing::SphereCloud(3000, 1.0, Vec3d(-3, 0, 0));
  const PointCloud b = testing::SphereCloud(3000, 0.5, Vec3d(3, 0, 0));
  a.positions.insert(a.positions.end(), b.positions.begin(), b.positions.end());
  a.normals.insert(a.normals.end(), b.normals.begin(), b.normals.end());
  LocalJobContext ctx;
  auto normals = EstimateNormals(a.positions, {}, ctx);
  ASSERT_TRUE(normals.ok());
  EXPECT_EQ(Compare(*normals, a.normals).flipped, 0);
}

// A plate whose thickness is about the spacing of its samples: each point's nearest neighbours
// hold both faces, whose normals are parallel. Orientation must turn the two faces apart, not
// copy one face's sign onto the other (as it did, leaving one face all inward).
TEST(Normals, ThinPlateFacesPointApart) {
  const double a = 0.05, b = a * 2 / 3, c = 7.2e-4;  // The bench plate cut to a sixth of its sides.
  TriangleMesh plate;
  const Eigen::Matrix3d turn =
      (Eigen::AngleAxisd(0.54, Vec3d::UnitZ()) * Eigen::AngleAxisd(-0.30, Vec3d::UnitY())).toRotationMatrix();
  for (int k = 0; k < 8; ++k) {
    plate.vertices.push_back((turn * Vec3d((k & 1) ? a : -a, (k & 2) ? b : -b, (k & 4) ? c : -c)).cast<float>());
  }
  plate.faces = {{0, 2, 1}, {1, 2, 3}, {4, 5, 6}, {5, 7, 6}, {0, 1, 4}, {1, 5, 4},
                 {2, 6, 3}, {3, 6, 7}, {0, 4, 2}, {2, 4, 6}, {1, 3, 5}, {3, 7, 5}};
  const PointCloud cloud = SampleCloud(plate, 5'600, 7, 0.0, false);
  const double spacing = std::sqrt(8 * a * b / static_cast<double>(cloud.size()));
  ASSERT_GT(spacing, 2 * c);  // Thinner than the spacing (by 7 %).
  LocalJobContext ctx;
  auto normals = EstimateNormals(cloud.positions, {}, ctx);
  ASSERT_TRUE(normals.ok()) << normals.status();
  const Vec3f up = (turn * Vec3d::UnitZ()).cast<float>();
  // Per face (below, above): points, and those turned the wrong way, all and 3 spacings in.
  int faces[2] = {0, 0}, flipped[2] = {0, 0}, inner[2] = {0, 0}, inner_flipped[2] = {0, 0};
  for (size_t i = 0; i < cloud.size(); ++i) {
    const float side = cloud.normals[i].dot(up);
    if (std::abs(side) < 0.5f) continue;  // The rim, a row of points that no normal fits.
    const bool wrong = (*normals)[i].dot(cloud.normals[i]) < 0;
    ++faces[side > 0];
    flipped[side > 0] += wrong;
    const Vec3d local = turn.transpose() * cloud.positions[i].cast<double>();
    if (std::min(a - std::abs(local.x()), b - std::abs(local.y())) < 3 * spacing) continue;
    ++inner[side > 0];
    inner_flipped[side > 0] += wrong;
  }
  for (int side = 0; side < 2; ++side) {
    std::printf("  %s: %d of %d points flipped; %d of the %d 3 spacings in\n", side ? "above" : "below", flipped[side],
                faces[side], inner_flipped[side], inner[side]);
    EXPECT_LT(flipped[side], faces[side] / 20);
    EXPECT_EQ(inner_flipped[side], 0);
  }
}

TEST(Normals, RejectsBadInput) {
  LocalJobContext ctx;
  std::vector<Vec3f> two = {Vec3f::Zero(), Vec3f::UnitX()};
  EXPECT_EQ(EstimateNormals(two, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  NormalEstimationParams bad;
  bad.neighbors = 1;
  EXPECT_EQ(EstimateNormals(testing::SphereCloud(100).positions, bad, ctx).status().code(),
            absl::StatusCode::kInvalidArgument);
  bad = {};
  bad.scales = 5;
  EXPECT_EQ(EstimateNormals(testing::SphereCloud(100).positions, bad, ctx).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(Normals, StopsWhenCancelled) {
  LocalJobContext ctx;
  ctx.Cancel();
  EXPECT_EQ(EstimateNormals(testing::SphereCloud(5000).positions, {}, ctx).status().code(),
            absl::StatusCode::kCancelled);
}

// Repeats of a position are dropped before any neighbour search, the first of each kept with
// its normal and attributes, the others in their order.
TEST(Normals, RepeatedPositionsAreRemovedFirstKeepingEachFirstPoint) {
  const PointCloud sphere = testing::SphereCloud(3000);
  PointCloud repeated;
  repeated.attributes.push_back({"index", {}});
  std::mt19937 random(7);
  std::uniform_int_distribution<size_t> any(0, sphere.size() - 1);
  auto add = [&](size_t i, Vec3f normal) {
    repeated.positions.push_back(sphere.positions[i]);
    repeated.normals.push_back(normal);
    repeated.attributes[0].values.push_back(static_cast<float>(i));
  };
  for (size_t i = 0; i < sphere.size(); ++i) add(i, sphere.normals[i]);
  for (int r = 0; r < 9000; ++r) add(any(random), -Vec3f::UnitX());  // Repeats, after their first.
  EXPECT_EQ(RemoveDuplicatePoints(repeated), 9000u);
  ASSERT_EQ(repeated.size(), sphere.size());
  ASSERT_EQ(repeated.normals.size(), sphere.size());
  ASSERT_EQ(repeated.attributes[0].values.size(), sphere.size());
  for (size_t i = 0; i < sphere.size(); ++i) {
    EXPECT_EQ(repeated.positions[i], sphere.positions[i]);
    EXPECT_EQ(repeated.normals[i], sphere.normals[i]);
    EXPECT_EQ(repeated.attributes[0].values[i], static_cast<float>(i));
  }
  // A repeat before the rest of the cloud: the first of each position wins, wherever it stands.
  PointCloud mixed;
  mixed.positions = {Vec3f(0, 0, 1), Vec3f(1, 0, 0), Vec3f(0, 0, 1), Vec3f(0, 1, 0), Vec3f(1, 0, 0)};
  EXPECT_EQ(RemoveDuplicatePoints(mixed), 2u);
  EXPECT_EQ(mixed.positions, (std::vector<Vec3f>{Vec3f(0, 0, 1), Vec3f(1, 0, 0), Vec3f(0, 1, 0)}));
  PointCloud distinct = testing::SphereCloud(500);
  const std::vector<Vec3f> before = distinct.positions;
  EXPECT_EQ(RemoveDuplicatePoints(distinct), 0u);
  EXPECT_EQ(distinct.positions, before);
}

}  // namespace
}  // namespace lsqsurf::core

namespace lsqsurf::core {
namespace {

TEST(NormalEstimation, ASingleViewsNormalsFaceItsSensor) {
  for (const Vec3d& eye : {Vec3d(0, -2.5, 1.6), Vec3d(1.8, 1.2, 0.9)}) {
    const PointCloud view = testing::BallOnATableView(eye);
    ASSERT_GT(view.size(), 9000u);
    LocalJobContext ctx;
    NormalEstimationParams params;
    params.viewpoints = {eye};
    NormalOrientation orientation;
    auto normals = EstimateNormals(view.positions, params, ctx, &orientation);
    ASSERT_TRUE(normals.ok()) << normals.status();
    // The camera sees every point it measured.
    std::printf("  hidden from the camera: %.4f\n", orientation.hidden_share);
    EXPECT_TRUE(orientation.toward_viewpoints);
    EXPECT_GE(orientation.hidden_share, 0);
    EXPECT_LT(orientation.hidden_share, 0.02);
    const AngleReport report = Compare(*normals, view.normals);
    // Where the ball meets the table and at its silhouette a PCA normal may lean, but none is
    // turned away from the camera.
    EXPECT_EQ(report.flipped, 0) << "of " << view.size();
    EXPECT_LT(report.mean_degrees, 3.0);
    for (size_t i = 0; i < view.size(); ++i) {
      ASSERT_GE((*normals)[i].cast<double>().dot(eye - view.positions[i].cast<double>()), -1e-3) << i;
    }
  }
}

// Two stations' scans of one scene, merged: each point's normal faces its own scanner. With the
// first station's position for all, the second's far side turns the wrong way.
TEST(NormalEstimation, MergedStationsNormalsFaceEachPointsOwnScanner) {
  const Vec3d eyes[2] = {Vec3d(0, -2.5, 1.6), Vec3d(0.4, 2.6, 1.4)};
  PointCloud merged;
  std::vector<uint32_t> station;
  for (uint32_t s = 0; s < 2; ++s) {
    const PointCloud view = testing::BallOnATableView(eyes[s]);
    merged.positions.insert(merged.positions.end(), view.positions.begin(), view.positions.end());
    merged.normals.insert(merged.normals.end(), view.normals.begin(), view.normals.end());
    station.insert(station.end(), view.size(), s);
  }
  LocalJobContext ctx;
  NormalEstimationParams params;
  params.viewpoints = {eyes[0], eyes[1]};
  params.station = station;
  NormalOrientation each_own;
  auto normals = EstimateNormals(merged.positions, params, ctx, &each_own);
  ASSERT_TRUE(normals.ok()) << normals.status();
  EXPECT_TRUE(each_own.toward_viewpoints);  // Each point seen from its own station.
  EXPECT_LT(each_own.hidden_share, 0.02);
  const AngleReport report = Compare(*normals, merged.normals);
  EXPECT_LT(report.flipped, static_cast<int>(merged.size() / 1000)) << "of " << merged.size();

  // With the first station's position for all, the second's far side turns the wrong way; that
  // position hides the ball's far side and the table behind it (12 % of the points), under the
  // default's limit, but not under a limit of 5 %: then it only chooses the sign of what
  // propagation orients, which turns more normals wrong here, where the ball meets the table.
  params.station.clear();
  params.max_hidden_share = 0.05;
  NormalOrientation orientation;
  auto one_eye = EstimateNormals(merged.positions, params, ctx, &orientation);
  ASSERT_TRUE(one_eye.ok());
  std::printf("  hidden from the first station: %.4f\n", orientation.hidden_share);
  EXPECT_GT(orientation.hidden_share, 0.08);
  EXPECT_FALSE(orientation.toward_viewpoints);
  const int set_aside = Compare(*one_eye, merged.normals).flipped;
  EXPECT_LT(set_aside, static_cast<int>(merged.size() / 10));  // The sign the first station sees.
  params.max_hidden_share = NormalEstimationParams{}.max_hidden_share;
  one_eye = EstimateNormals(merged.positions, params, ctx, &orientation);
  ASSERT_TRUE(one_eye.ok());
  EXPECT_TRUE(orientation.toward_viewpoints);
  const int trusted = Compare(*one_eye, merged.normals).flipped;
  std::printf("  flipped: %d set aside, %d trusted, of %zu\n", set_aside, trusted, merged.size());
  EXPECT_GT(trusted, static_cast<int>(merged.size() / 100));
  EXPECT_LT(trusted, set_aside);

  params.station = station;
  params.viewpoints = {eyes[0]};
  EXPECT_EQ(EstimateNormals(merged.positions, params, ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::core
