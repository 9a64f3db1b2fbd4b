#include "worker/volume/volume_isosurface.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "tests/volume/build_field.h"
#include "worker/core/mesh_metrics.h"
#include "worker/volume/synthetic.h"

namespace lsqsurf::volume {
namespace {

// First-order distance of x to {f = iso}: |f(x) − iso| / |∇f(x)|.
double LevelDistance(const AnalyticField& f, const Vec3d& x, double iso) {
  return std::abs(f.value(x) - iso) / f.gradient(x).norm();
}

TEST(VolumeIsosurface, SphereLevelOfARadialFieldIsClosedAndRound) {
  const core::Box3 box(Vec3d::Zero(), Vec3d::Ones());
  const AnalyticField radial{"r", [](const Vec3d& x) { return (x - Vec3d(0.5, 0.5, 0.5)).norm(); }, nullptr, box};
  VolumeMesh mesh = JitteredTetMesh(box, 17, 0.3, 9);
  SampleField(mesh, radial);
  auto field = Build(mesh, "r");
  ASSERT_NE(field, nullptr);
  core::LocalJobContext ctx;
  VolumeIsosurfaceParams params;
  params.iso_values = {0.3};
  auto mesh_or = ExtractVolumeIsosurface(*field, params, ctx);
  ASSERT_TRUE(mesh_or.ok()) << mesh_or.status();
  const core::TriangleMesh welded = core::WeldByPosition(*mesh_or);
  const core::MeshTopology topo = core::AnalyzeTopology(welded);
  EXPECT_TRUE(topo.watertight());
  EXPECT_EQ(topo.components, 1);
  EXPECT_EQ(topo.euler_characteristic(), 2);
  const double volume = core::EnclosedVolume(*mesh_or);
  EXPECT_NEAR(volume, 4.0 / 3.0 * std::numbers::pi * 0.027, 0.01 * 4.0 / 3.0 * std::numbers::pi * 0.027);
  double worst = 0;
  for (size_t v = 0; v < mesh_or->vertices.size(); ++v) {
    const Vec3d x = mesh_or->vertices[v].cast<double>();
    worst = std::max(worst, std::abs((x - Vec3d(0.5, 0.5, 0.5)).norm() - 0.3));
    // Normals from Q_∇f point outwards, where r grows.
    EXPECT_GT(mesh_or->normals[v].cast<double>().dot(x - Vec3d(0.5, 0.5, 0.5)), 0);
  }
  EXPECT_LT(worst, 0.01);  // A sixth of the spacing.
}

TEST(VolumeIsosurface, FrankeLevelIsCloserThanTheLinearContourAndStaysInTheDomain) {
  const AnalyticField franke = Franke3d();
  VolumeMesh mesh = JitteredTetMesh(franke.domain, 25, 0.3, 3);
  SampleField(mesh, franke);
  auto field = Build(mesh, "franke");
  ASSERT_NE(field, nullptr);
  const double iso = 0.35;
  core::LocalJobContext ctx;
  VolumeIsosurfaceParams params;
  params.iso_values = {iso, 0.6};
  params.color_field = 0;
  auto surface = ExtractVolumeIsosurface(*field, params, ctx);
  ASSERT_TRUE(surface.ok()) << surface.status();
  ASSERT_EQ(surface->vertex_attributes.size(), 2u);
  EXPECT_EQ(surface->vertex_attributes[0].name, "iso");
  EXPECT_EQ(surface->vertex_attributes[1].name, "franke");
  double ours = 0;
  int ours_count = 0;
  for (size_t v = 0; v < surface->vertices.size(); ++v) {
    const Vec3d x = surface->vertices[v].cast<double>();
    EXPECT_TRUE(franke.domain.exteriorDistance(x) < 1e-6) << x.transpose();
    if (surface->vertex_attributes[0].values[v] != static_cast<float>(iso)) continue;
    // The colour attribute is Q_f itself here: on the level by construction.
    EXPECT_NEAR(surface->vertex_attributes[1].values[v], iso, 1e-3);
    ours += LevelDistance(franke, x, iso);
    ++ours_count;
  }
  // The linear contour's vertices: crossings of the level on the tetrahedra's edges.
  const VertexField& data = mesh.fields[0];
  double linear = 0;
  int linear_count = 0;
  for (const auto& t : Tetrahedralize(mesh)) {
    for (int a = 0; a < 4; ++a) {
      for (int b = a + 1; b < 4; ++b) {
        const double fa = data.values[t[a]] - iso, fb = data.values[t[b]] - iso;
        if ((fa < 0) == (fb < 0)) continue;
        const double s = fa / (fa - fb);
        const Vec3d x = (1 - s) * mesh.positions[t[a]].cast<double>() + s * mesh.positions[t[b]].cast<double>();
        linear += LevelDistance(franke, x, iso);
        ++linear_count;
      }
    }
  }
  ASSERT_GT(ours_count, 100);
  ours /= ours_count;
  linear /= linear_count;
  std::printf("mean level distance: iaMLS %.3g, linear %.3g\n", ours, linear);
  EXPECT_LT(ours, 0.5 * linear);
}

TEST(VolumeIsosurface, ALevelOutsideTheRangeIsRefusedWithTheRange) {
  const AnalyticField franke = Franke3d();
  VolumeMesh mesh = JitteredTetMesh(franke.domain, 9, 0.3, 3);
  SampleField(mesh, franke);
  auto field = Build(mesh, "franke");
  ASSERT_NE(field, nullptr);
  core::LocalJobContext ctx;
  VolumeIsosurfaceParams params;
  params.iso_values = {5};
  auto surface = ExtractVolumeIsosurface(*field, params, ctx);
  ASSERT_FALSE(surface.ok());
  EXPECT_NE(surface.status().message().find("spans ["), std::string::npos) << surface.status();
}

}  // namespace
}  // namespace lsqsurf::volume
