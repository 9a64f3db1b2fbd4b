#include "worker/extract/j1a.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>

namespace lsqsurf::extract {
namespace {

using namespace ::lsqsurf::core;  // The tests speak in core types throughout.

// Six times the volume, exactly, in vertex units.
int64_t SixVolume(const TetKeys& t) {
  std::array<std::array<int64_t, 3>, 3> m{};
  const auto a = UnpackVertex(t[0]);
  for (int r = 0; r < 3; ++r) {
    const auto p = UnpackVertex(t[static_cast<size_t>(r + 1)]);
    for (int k = 0; k < 3; ++k)
      m[static_cast<size_t>(r)][static_cast<size_t>(k)] =
          int64_t{p[static_cast<size_t>(k)]} - a[static_cast<size_t>(k)];
  }
  return m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
         m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
}

// A random adaptive tree: leaves near a sphere are refined, with random extra splits.
AdaptiveOctree RandomTree(uint64_t seed, int depth, bool balance) {
  AdaptiveOctree tree(Box3(Vec3d::Zero(), Vec3d::Ones()), depth);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  const double radius = 0.3 + 0.1 * u(rng);
  tree.Refine([&](const OctreeCell& c) {
    const double size = 1.0 / (1 << c.level);
    const Vec3d centre = (Vec3d(c.x, c.y, c.z) + Vec3d::Constant(0.5)) * size;
    const bool near = std::abs((centre - Vec3d::Constant(0.5)).norm() - radius) < size;
    return c.level < 1 || (near && u(rng) < 0.85) || u(rng) < 0.05;
  });
  if (balance) tree.Balance();
  return tree;
}

struct Census {
  size_t tets = 0;
  int64_t six_volume = 0;
  int64_t min_six_volume = INT64_MAX;
  size_t interior_faces = 0, boundary_faces = 0, bad_faces = 0;
};

Census Triangulate(const AdaptiveOctree& tree) {
  std::vector<TetKeys> tets;
  for (const OctreeCell& leaf : tree.Leaves()) AppendJ1aTetrahedra(tree, leaf, tets);
  Census c;
  c.tets = tets.size();
  std::vector<std::array<VertexKey, 3>> all_faces;
  all_faces.reserve(tets.size() * 4);
  for (const TetKeys& t : tets) {
    const int64_t v = SixVolume(t);
    c.six_volume += v;
    c.min_six_volume = std::min(c.min_six_volume, v);
    for (int skip = 0; skip < 4; ++skip) {
      std::array<VertexKey, 3> f{};
      int n = 0;
      for (int i = 0; i < 4; ++i) {
        if (i != skip) f[static_cast<size_t>(n++)] = t[static_cast<size_t>(i)];
      }
      std::sort(f.begin(), f.end());
      all_faces.push_back(f);
    }
  }
  std::sort(all_faces.begin(), all_faces.end());
  std::vector<std::pair<std::array<VertexKey, 3>, int>> faces;
  for (const auto& f : all_faces) {
    if (faces.empty() || faces.back().first != f) faces.emplace_back(f, 0);
    ++faces.back().second;
  }
  const uint32_t max = tree.CellUnits(0);
  for (const auto& [f, count] : faces) {
    // A face on the root boundary has all three vertices on one of its planes.
    bool on_boundary = false;
    for (int axis = 0; axis < 3; ++axis) {
      for (uint32_t plane : {0u, max}) {
        bool all = true;
        for (VertexKey k : f) all &= UnpackVertex(k)[static_cast<size_t>(axis)] == plane;
        on_boundary |= all;
      }
    }
    if (on_boundary) {
      ++c.boundary_faces;
      c.bad_faces += count != 1;
    } else {
      ++c.interior_faces;
      c.bad_faces += count != 2;
    }
  }
  return c;
}

TEST(J1a, UniformLeafHas48Tetrahedra) {
  AdaptiveOctree tree(Box3(Vec3d::Zero(), Vec3d::Ones()), 3);
  std::vector<TetKeys> tets;
  AppendJ1aTetrahedra(tree, OctreeCell{}, tets);
  EXPECT_EQ(tets.size(), 48u);
  tree.Refine([](const OctreeCell& c) { return c.level < 2; });
  const Census c = Triangulate(tree);
  EXPECT_EQ(c.tets, 48u * 64u);
  EXPECT_EQ(c.bad_faces, 0u);
}

TEST(J1a, RandomBalancedTreesAreConformingAndFillTheCube) {
  for (uint64_t seed = 1; seed <= 6; ++seed) {
    const AdaptiveOctree tree = RandomTree(seed, 5, /*balance=*/true);
    // 2:1 balance: touching leaves differ by at most one level.
    for (const OctreeCell& leaf : tree.Leaves()) {
      for (int d = 0; d < 27; ++d) {
        const int64_t x = int64_t{leaf.x} + d % 3 - 1, y = int64_t{leaf.y} + (d / 3) % 3 - 1,
                      z = int64_t{leaf.z} + d / 9 - 1;
        const int64_t n = int64_t{1} << leaf.level;
        if (x < 0 || y < 0 || z < 0 || x >= n || y >= n || z >= n) continue;
        const OctreeCell* other = tree.LeafContaining(
            {leaf.level, static_cast<uint32_t>(x), static_cast<uint32_t>(y), static_cast<uint32_t>(z)});
        if (other == nullptr) continue;  // The neighbour is finer: checked from its side.
        EXPECT_GE(other->level, leaf.level - 1);
      }
    }
    const Census c = Triangulate(tree);
    EXPECT_GT(c.tets, 48u * 100u) << "seed " << seed;
    EXPECT_EQ(c.bad_faces, 0u) << "seed " << seed;      // Every interior triangle in exactly 2 tets.
    EXPECT_GT(c.min_six_volume, 0) << "seed " << seed;  // Positively oriented, none flat.
    const int64_t side = tree.CellUnits(0);
    EXPECT_EQ(c.six_volume, 6 * side * side * side) << "seed " << seed;  // Exactly the root cube.
  }
}

TEST(J1a, VerticesAreSharedByKey) {
  AdaptiveOctree tree(Box3(Vec3d(-2, -2, -2), Vec3d(2, 2, 2)), 4);
  tree.Refine([](const OctreeCell& c) { return c.level < 1; });
  // The centre of the root is a corner of all 8 children and maps to the same model point.
  const uint32_t mid = tree.CellUnits(1);
  EXPECT_TRUE(tree.Position(PackVertex(mid, mid, mid)).isApprox(Vec3d::Zero()));
  EXPECT_TRUE(tree.Position(PackVertex(0, 0, 0)).isApprox(Vec3d(-2, -2, -2)));
}

}  // namespace
}  // namespace lsqsurf::extract
