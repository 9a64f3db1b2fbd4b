#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "worker/render/render.h"

namespace lsqsurf::render {
namespace {

using core::Vec3d;

// An n³ grid over [−1, 1]³ of a field and its gradient.
VolumeGrid Grid(int n, const std::function<double(const Vec3d&)>& f, const std::function<Vec3d(const Vec3d&)>& g) {
  VolumeGrid grid;
  grid.dims = {n, n, n};
  grid.origin = Vec3d::Constant(-1);
  grid.spacing = Vec3d::Constant(2.0 / (n - 1));
  for (int k = 0; k < n; ++k) {
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        const Vec3d x = grid.origin + grid.spacing.cwiseProduct(Vec3d(i, j, k));
        grid.values.push_back(static_cast<float>(f(x)));
        grid.gradients.push_back(g(x).cast<float>());
      }
    }
  }
  return grid;
}

TEST(RaycastVolume, IsosurfaceOfARadialFieldHasTheSphereSilhouette) {
  const VolumeGrid grid = Grid(
      64, [](const Vec3d& x) { return x.norm(); },
      [](const Vec3d& x) { return x.norm() > 0 ? Vec3d(x.normalized()) : Vec3d::Zero(); });
  RenderParams p;
  p.width = p.height = 512;
  p.volume_mode = VolumeMode::kIsosurface;
  p.iso_value = 0.5;
  auto image = RaycastVolume(grid, p);
  ASSERT_TRUE(image.ok()) << image.status();
  int covered = 0;
  for (int y = 0; y < 512; ++y) {
    for (int x = 0; x < 512; ++x) covered += image->At(x, y)[0] != 255 || image->At(x, y)[1] != 255;
  }
  // The camera frames the box's bounding sphere (radius √3) with a 30° field of view; the
  // sphere of radius 0.5 then subtends a cone of half-angle asin(0.5 / D).
  const double distance = 1.02 * std::sqrt(3.0) / std::sin(15 * std::numbers::pi / 180);
  const double radius_px = std::tan(std::asin(0.5 / distance)) / std::tan(15 * std::numbers::pi / 180) * 256;
  EXPECT_NEAR(covered, std::numbers::pi * radius_px * radius_px, 0.03 * std::numbers::pi * radius_px * radius_px);
  // Lit from the camera: the middle faces it and is the brightest.
  EXPECT_GT(image->At(256, 256)[0], image->At(256 + static_cast<int>(0.9 * radius_px), 256)[0]);
}

TEST(RaycastVolume, ConstantOpacityGathersAlongTheChord) {
  const VolumeGrid grid = Grid(
      64, [](const Vec3d&) { return 1.0; }, [](const Vec3d&) { return Vec3d::Zero(); });
  RenderParams p;
  p.width = p.height = 64;
  p.camera.azimuth_deg = 0;
  p.camera.elevation_deg = 0;
  p.transparent = true;
  p.opacity = "0:0.02,1:0.02";
  auto image = RaycastVolume(grid, p);
  ASSERT_TRUE(image.ok()) << image.status();
  // The central ray crosses the box along x: a chord of 2, i.e. 63 cells of opacity 0.02 each.
  const double expected = 1 - std::pow(0.98, 63.0);
  EXPECT_NEAR(image->At(32, 32)[3] / 255.0, expected, 0.015);
  EXPECT_EQ(image->At(0, 0)[3], 0);  // Outside the box nothing is gathered.
}

TEST(RaycastVolume, OutsideTheDataRaysPassThrough) {
  // NaN marks points outside the data: a field defined only for x < 0 shows only that half.
  const VolumeGrid grid = Grid(
      32, [](const Vec3d& x) { return x.x() < 0 ? 1.0 : std::nan(""); }, [](const Vec3d&) { return Vec3d::Zero(); });
  RenderParams p;
  p.width = p.height = 64;
  p.camera.azimuth_deg = 90;  // The camera on +y looking back: +x points to the left of the picture.
  p.camera.elevation_deg = 0;
  p.transparent = true;
  p.opacity = "0:0.2,1:0.2";
  auto image = RaycastVolume(grid, p);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_GT(image->At(40, 32)[3], 200);
  EXPECT_EQ(image->At(24, 32)[3], 0);
}

TEST(RaycastVolume, OpacityTextIsCheckedWithAReason) {
  EXPECT_TRUE(ParseOpacity("0:0,0.5:0.05,1:0.4").ok());
  EXPECT_FALSE(ParseOpacity("").ok());
  EXPECT_FALSE(ParseOpacity("0:0,1:2").ok());
  EXPECT_FALSE(ParseOpacity("0.5:0,0.2:0.1").ok());
  EXPECT_NE(std::string(ParseOpacity("a:b").status().message()).find("'a:b'"), std::string::npos);
}

}  // namespace
}  // namespace lsqsurf::render
