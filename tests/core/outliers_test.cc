#include "worker/core/outliers.h"

#include <gtest/gtest.h>

#include <random>

#include "tests/test_shapes.h"

namespace lsqsurf::core {
namespace {

size_t Removed(PointCloud cloud) {
  LocalJobContext ctx;
  auto removed = RemoveIsolatedPoints(cloud, {}, ctx);
  EXPECT_TRUE(removed.ok()) << removed.status();
  return removed.ok() ? *removed : 0;
}

// Clouds without a stray point lose none, or next to none where random sampling leaves a gap
// around a point: even density, a thin tube and a drilled CAD part sampled at random, and a
// camera's view whose density falls five-fold from the near table to the far one.
TEST(IsolatedPoints, CleanCloudsLoseNextToNone) {
  EXPECT_EQ(Removed(testing::SphereCloud(20000)), 0u);
  EXPECT_LE(Removed(testing::TorusCloud(20000, 1.0, 0.1)), 2u);
  EXPECT_LE(Removed(testing::DrilledBlockCloud(20000)), 2u);
  EXPECT_EQ(Removed(testing::BallOnATableView(Vec3d(0, -2.5, 1.6))), 0u);
}

// Stray points off a sphere, 6 to 16 of its spacings away (a depth camera's flying pixels
// beside an object's silhouette) go, and only they: each point carries its index to tell which
// went. (Strays far from any surface and as dense among themselves as their distance to it
// look like a sparse surface of their own, and stay.)
TEST(IsolatedPoints, StrayPointsGoAndOnlyThey) {
  PointCloud cloud = testing::SphereCloud(20000);
  cloud.normals.clear();
  std::mt19937_64 rng(4);
  std::uniform_real_distribution<double> radius(1.15, 1.4);
  std::normal_distribution<double> direction(0, 1);
  const size_t strays = 200;
  for (size_t i = 0; i < strays; ++i) {
    const Vec3d d = Vec3d(direction(rng), direction(rng), direction(rng)).normalized();
    cloud.positions.push_back((radius(rng) * d).cast<float>());
  }
  cloud.attributes.push_back({"index", {}});
  for (size_t i = 0; i < cloud.size(); ++i) cloud.attributes[0].values.push_back(static_cast<float>(i));
  LocalJobContext ctx;
  auto removed = RemoveIsolatedPoints(cloud, {}, ctx);
  ASSERT_TRUE(removed.ok());
  EXPECT_GE(*removed, strays * 9 / 10);
  size_t sphere_points = 0;
  for (float index : cloud.attributes[0].values) sphere_points += index < 20000;
  EXPECT_EQ(sphere_points, 20000u);  // Not one of the sphere's.
  EXPECT_EQ(cloud.size(), 20000 + strays - *removed);
}

}  // namespace
}  // namespace lsqsurf::core
