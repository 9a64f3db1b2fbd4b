#include "worker/core/kd_tree.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <thread>

#include "worker/core/local_spacing.h"

namespace lsqsurf::core {
namespace {

std::vector<Vec3f> RandomPoints(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(-1, 1);
  std::vector<Vec3f> pts(n);
  for (auto& p : pts) p = Vec3f(u(rng), u(rng), u(rng));
  return pts;
}

std::vector<std::pair<float, uint32_t>> BruteForce(const std::vector<Vec3f>& pts, const Vec3f& q) {
  std::vector<std::pair<float, uint32_t>> all;
  for (uint32_t i = 0; i < pts.size(); ++i) all.emplace_back((pts[i] - q).squaredNorm(), i);
  std::sort(all.begin(), all.end());
  return all;
}

TEST(KdTree, KnnMatchesBruteForce) {
  const auto pts = RandomPoints(5000, 1);
  KdTree tree(pts);
  const auto queries = RandomPoints(200, 2);
  std::vector<Neighbor> nn;
  for (const auto& q : queries) {
    tree.Knn(q, 10, nn);
    const auto truth = BruteForce(pts, q);
    ASSERT_EQ(nn.size(), 10u);
    for (size_t i = 0; i < 10; ++i) {
      EXPECT_NEAR(nn[i].distance2, truth[i].first, 1e-6f);
    }
  }
}

TEST(KdTree, RadiusMatchesBruteForce) {
  const auto pts = RandomPoints(5000, 3);
  KdTree tree(pts);
  std::vector<Neighbor> nn;
  for (const auto& q : RandomPoints(100, 4)) {
    tree.Radius(q, 0.2f, nn);
    std::vector<uint32_t> got;
    for (const auto& n : nn) got.push_back(n.index);
    std::sort(got.begin(), got.end());
    std::vector<uint32_t> want;
    for (const auto& [d2, i] : BruteForce(pts, q)) {
      if (d2 <= 0.04f) want.push_back(i);
    }
    std::sort(want.begin(), want.end());
    EXPECT_EQ(got, want);
  }
}

TEST(KdTree, ConcurrentQueriesAgreeWithSerialOnes) {
  const auto pts = RandomPoints(20000, 5);
  KdTree tree(pts);
  const auto queries = RandomPoints(2000, 6);
  std::vector<uint32_t> serial(queries.size()), parallel(queries.size());
  for (size_t i = 0; i < queries.size(); ++i) serial[i] = tree.Nearest(queries[i]).index;
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      std::vector<Neighbor> nn;
      for (size_t i = static_cast<size_t>(t); i < queries.size(); i += 4) {
        tree.Radius(queries[i], 0.1f, nn);  // Exercises the per-thread buffer too.
        parallel[i] = tree.Nearest(queries[i]).index;
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(serial, parallel);
}

TEST(KdTree, EmptySetAnswersNothing) {
  std::vector<Vec3f> none;
  KdTree tree(none);
  std::vector<Neighbor> nn;
  tree.Knn(Vec3f::Zero(), 3, nn);
  EXPECT_TRUE(nn.empty());
  tree.Radius(Vec3f::Zero(), 1.0f, nn);
  EXPECT_TRUE(nn.empty());
}

// A plane sampled on a grid of 0.01 for x < 0 and of 0.04 for x > 0 (a lidar's near and far side):
// the local spacing follows the grid, so the same height above the plane is unmeasured over the
// dense half and measured over the sparse one.
TEST(LocalSpacing, FollowsTheCloudsDensityWhereItIs) {
  std::vector<Vec3f> plane;
  for (int i = -100; i < 0; ++i) {
    for (int j = 0; j < 50; ++j) plane.emplace_back(0.01f * static_cast<float>(i), 0.01f * static_cast<float>(j), 0);
  }
  for (int i = 1; i <= 25; ++i) {
    for (int j = 0; j < 13; ++j) plane.emplace_back(0.04f * static_cast<float>(i), 0.04f * static_cast<float>(j), 0);
  }
  const KdTree tree(plane);
  const LocalSpacing spacing(tree);
  std::vector<Neighbor> scratch;
  const auto dense = spacing.At(Vec3f(-0.5f, 0.25f, 0.05f), scratch);
  const auto sparse = spacing.At(Vec3f(0.5f, 0.24f, 0.05f), scratch);
  EXPECT_NEAR(dense.spacing, 0.01, 1e-6);
  EXPECT_NEAR(sparse.spacing, 0.04, 1e-6);
  EXPECT_NEAR(dense.nearest, 0.05, 1e-6);
  EXPECT_TRUE(dense.Unmeasured());
  EXPECT_FALSE(sparse.Unmeasured());
  // On the cloud itself nothing is beyond.
  EXPECT_FALSE(spacing.At(plane[123], scratch).Beyond(0.5));
  // 5,000 of the 5,325 points are on the dense grid: the cloud's one spacing is the dense one,
  // which is why a global rule calls the sparse half unmeasured.
  EXPECT_NEAR(spacing.MedianNearest(), 0.01, 1e-6);
}

}  // namespace
}  // namespace lsqsurf::core
