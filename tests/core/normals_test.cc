#include "worker/core/normals.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "tests/test_shapes.h"

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

TEST(Normals, RejectsBadInput) {
  LocalJobContext ctx;
  std::vector<Vec3f> two = {Vec3f::Zero(), Vec3f::UnitX()};
  EXPECT_EQ(EstimateNormals(two, {}, ctx).status().code(), absl::StatusCode::kInvalidArgument);
  NormalEstimationParams bad;
  bad.neighbors = 1;
  EXPECT_EQ(EstimateNormals(testing::SphereCloud(100).positions, bad, ctx).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(Normals, StopsWhenCancelled) {
  LocalJobContext ctx;
  ctx.Cancel();
  EXPECT_EQ(EstimateNormals(testing::SphereCloud(5000).positions, {}, ctx).status().code(),
            absl::StatusCode::kCancelled);
}

}  // namespace
}  // namespace lsqsurf::core
