#include "worker/core/noise.h"

#include <gtest/gtest.h>

#include <random>

namespace lsqsurf::core {
namespace {

// Both faces of a plate, `thickness` apart, with their outward normals, and Gaussian noise of
// `sigma` along them.
void PlateCloud(double thickness, double sigma, std::vector<Vec3f>& points, std::vector<Vec3f>& normals) {
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> unit(-0.5, 0.5);
  std::normal_distribution<double> gauss(0, 1);
  for (int i = 0; i < 40000; ++i) {
    const double side = i % 2 == 0 ? 1.0 : -1.0;
    const double z = side * (0.5 * thickness + sigma * gauss(rng));
    points.emplace_back(static_cast<float>(unit(rng)), static_cast<float>(unit(rng)), static_cast<float>(z));
    normals.emplace_back(0.0f, 0.0f, static_cast<float>(side));
  }
}

// A plate thinner than a neighbourhood (here 0.002 against 48 neighbours spanning ~0.02) is two
// sheets, not noise: the estimate reads each point's own sheet.
TEST(Noise, AThinPlateIsTwoCleanSheetsAndItsNoiseIsStillSeen) {
  std::vector<Vec3f> points, normals;
  PlateCloud(0.002, 0.0, points, normals);
  const KdTree clean(points);
  EXPECT_LT(EstimateNoise(clean, normals).sigma, 1e-6);

  std::vector<Vec3f> noisy_points, noisy_normals;
  PlateCloud(0.002, 2e-4, noisy_points, noisy_normals);
  const KdTree noisy(noisy_points);
  EXPECT_NEAR(EstimateNoise(noisy, noisy_normals).sigma, 2e-4, 0.3e-4);
}

}  // namespace
}  // namespace lsqsurf::core
