// Tiled PU where the untiled extraction refines its leaves (corners, acute creases, thin walls):
// forced into many tiles, the raw marching is the untiled one face for face and the finished
// surfaces agree. Slow (a minute): every tile reads most of its small cloud.
#include <gtest/gtest.h>

#include <cstdio>
#include <vector>

#include "tests/polyhedra.h"
#include "tests/pu/tiled_compare.h"
#include "tests/test_shapes.h"
#include "worker/core/sampling.h"

namespace lsqsurf::pu {
namespace {

using compare::ClosingHoles;
using compare::ExpectSameMesh;
using compare::ExpectSameSurface;
using compare::RawMarching;
using compare::RunBoth;
using compare::Runs;

// The shapes the untiled extraction gives finer leaves (corners, acute creases, thin walls),
// forced into many tiles: the raw marching is the untiled one face for face, and the finished
// surfaces agree.
struct FineLeafCase {
  const char* name;
  core::PointCloud cloud;
  int64_t tile_points;
};

std::vector<FineLeafCase> FineLeafCases() {
  std::vector<FineLeafCase> cases;
  const std::vector<core::Vec3d> tetrahedron = {core::Vec3d(1, 1, 1).normalized(), core::Vec3d(1, -1, -1).normalized(),
                                                core::Vec3d(-1, 1, -1).normalized(),
                                                core::Vec3d(-1, -1, 1).normalized()};
  cases.push_back(
      {"tetrahedron (70.5 degree edges)", testing::TurnedPolyhedron(tetrahedron, 0.2).Sample(30'000), 8'000});
  std::vector<testing::Capsule> fingers;
  cases.push_back({"hand with thin fingers", testing::HandCloud(0.004, fingers), 40'000});
  const core::TriangleMesh plate = testing::TurnedPlate(0.05, 0.0375, 0.00072);
  cases.push_back({"thin plate", core::SampleCloud(plate, 6'250, 7, 0.0, false), 2'000});
  return cases;
}

TEST(PuTiles, FineLeavesInManyTilesAreTheUntiledOnes) {
  for (const FineLeafCase& c : FineLeafCases()) {
    SCOPED_TRACE(c.name);
    std::printf("%s\n", c.name);
    const PuTileParams tiles{.tile_points = c.tile_points, .support_cap = 16};
    const Runs raw = RunBoth(c.cloud, RawMarching(), tiles);
    EXPECT_GE(raw.stats.tiles, 4);
    ExpectSameMesh(raw.whole, raw.tiled, 1e-9 * raw.diagonal);
    const Runs finished = RunBoth(c.cloud, ClosingHoles({}), tiles);
    ExpectSameSurface(finished, 1e-6);
  }
}

}  // namespace
}  // namespace lsqsurf::pu
