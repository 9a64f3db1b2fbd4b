// The mesh a client decodes keeps the engine's topology: decoded with Draco and merged by
// position (as STL export and most tools do), it is as closed and manifold as the engine's own
// mesh, and the job's statistics describe it.
#include "tests/jobs/delivered_mesh.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <numbers>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/sphere_mesh.h"
#include "worker/core/strings.h"
#include "worker/csg/csg.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/surface_job.h"
#include "worker/jobs/surface_points.h"

namespace lsqsurf::jobs {
namespace {

TEST(DeliveredMesh, ACadPartFromOneHundredThousandPoints) {
  ExpectDeliveredKeepsTopology("pu", testing::DrilledBlockCloud(100'000), /*genus=*/1);
}

// A cloud over tile_points goes tile by tile; the client still gets one closed mesh.
TEST(DeliveredMesh, ATiledCadPartIsOneClosedMesh) {
  core::ParamSet params = *DefaultParams("pu");
  ASSERT_TRUE(params.Set("tile_points", 3000).ok());
  ASSERT_TRUE(params.Set("support_cap", 16).ok());
  Statistics statistics;
  ExpectDeliveredKeepsTopology("pu", testing::DrilledBlockCloud(20'000, 2.0, 0.6, 0.3, 0.3), /*genus=*/1, &params,
                               &statistics);
  EXPECT_GE(Statistic(statistics, "tiles"), 4);
  EXPECT_GT(Statistic(statistics, "seam_vertices"), 0);
}

// A cloud of few positions, each repeated hundreds of thousands of times (a 400-byte Draco upload
// can declare that many), costs no neighbour search, which scanned all the repeats each time:
// three positions are refused, thirty are a cloud of thirty points.
TEST(DeliveredMesh, ACloudOfRepeatedPositionsCostsNoNeighbourSearch) {
  core::PointCloud repeats;
  for (int i = 0; i < 2'000'000; ++i) repeats.positions.emplace_back(float(i % 3), 0.0f, 0.0f);
  core::LocalJobContext ctx;
  auto refused = ReconstructSurface("iamls", *DefaultParams("iamls"), repeats, ctx);
  ASSERT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  EXPECT_NE(refused.status().message().find("1999997 points repeat"), std::string::npos) << refused.status();
  for (int i = 0; i < 2'000'000; ++i) repeats.positions[i] = {float(i % 5), float(i % 3), 0.5f * float(i % 2)};
  auto thirty = ReconstructSurface("iamls", *DefaultParams("iamls"), repeats, ctx);
  if (thirty.ok()) {
    EXPECT_EQ(Statistic(thirty->statistics, "duplicate_points"), 1999970);
  }

  // Every point of a sphere three times gives the sphere's own surface, and says so.
  const core::PointCloud sphere = testing::SphereCloud(3000);
  core::PointCloud tripled = sphere;
  for (int copy = 0; copy < 2; ++copy) {
    tripled.positions.insert(tripled.positions.end(), sphere.positions.begin(), sphere.positions.end());
    tripled.normals.insert(tripled.normals.end(), sphere.normals.begin(), sphere.normals.end());
  }
  auto once = ReconstructSurface("iamls", *DefaultParams("iamls"), sphere, ctx);
  auto thrice = ReconstructSurface("iamls", *DefaultParams("iamls"), tripled, ctx);
  ASSERT_TRUE(once.ok() && thrice.ok());
  auto sorted = [](std::vector<core::Vec3f> v) {  // The extraction's threads may order them otherwise.
    std::sort(v.begin(), v.end(), [](const core::Vec3f& a, const core::Vec3f& b) {
      return std::lexicographical_compare(a.data(), a.data() + 3, b.data(), b.data() + 3);
    });
    return v;
  };
  EXPECT_EQ(sorted(thrice->mesh.vertices), sorted(once->mesh.vertices));
  EXPECT_EQ(Statistic(thrice->statistics, "duplicate_points"), 6000);
  EXPECT_EQ(Statistic(thrice->statistics, "input_points"), 9000);
}

// A sphere scanned all round but its north cap (a region no view reached) comes back open by
// default, and closed on request: one closed component through PU and iaMLS alike, near the
// sphere where the data were, with the vertices of the cap marked `filled` and those under the
// points not.
TEST(DeliveredMesh, AnOpenCloudClosesOnRequestAndTheFillingIsMarked) {
  core::PointCloud open = testing::SphereCloud(20'000);
  for (size_t i = open.size(); i-- > 0;) {
    if (open.positions[i].z() > 0.7f) {
      open.positions.erase(open.positions.begin() + static_cast<std::ptrdiff_t>(i));
      open.normals.erase(open.normals.begin() + static_cast<std::ptrdiff_t>(i));
    }
  }
  for (const std::string method : {"pu", "iamls"}) {
    SCOPED_TRACE(method);
    core::ParamSet params = *DefaultParams(method);
    ASSERT_TRUE(params.Set("fill_holes", true).ok());
    Statistics statistics;
    ExpectDeliveredKeepsTopology(method, open, /*genus=*/0, &params, &statistics);
    EXPECT_GE(Statistic(statistics, "holes_filled"), 1);
    EXPECT_EQ(Statistic(statistics, "holes_left"), 0);

    core::LocalJobContext ctx;
    auto result = ReconstructSurface(method, params, open, ctx);
    ASSERT_TRUE(result.ok()) << result.status();
    EXPECT_EQ(core::AnalyzeTopology(result->mesh).components, 1);
    // Left as they are, the methods keep the cap open.
    auto unfilled = ReconstructSurface(method, *DefaultParams(method), open, ctx);
    ASSERT_TRUE(unfilled.ok()) << unfilled.status();
    EXPECT_GE(core::AnalyzeTopology(unfilled->mesh).boundary_loops, 1);
    const auto filled =
        std::ranges::find(result->mesh.vertex_attributes, std::string(kFilledAttribute), &core::ScalarAttribute::name);
    ASSERT_NE(filled, result->mesh.vertex_attributes.end());
    ASSERT_EQ(filled->values.size(), result->mesh.vertices.size());
    size_t cap = 0, cap_marked = 0, measured = 0, measured_marked = 0;
    for (size_t v = 0; v < result->mesh.vertices.size(); ++v) {
      const core::Vec3f& x = result->mesh.vertices[v];
      EXPECT_NEAR(x.norm(), 1.0, 0.1) << "vertex " << v;
      if (x.z() > 0.85f) ++cap, cap_marked += filled->values[v] == 1.0f;
      if (x.z() < 0.6f) ++measured, measured_marked += filled->values[v] == 1.0f;
    }
    EXPECT_GT(cap, 50u);
    EXPECT_EQ(cap_marked, cap);
    EXPECT_EQ(measured_marked, 0u) << "of " << measured;
  }
}

// A unit sphere with a sphere of radius 0.3 inside it and one of radius 0.3 beside it: the inner
// one goes where it is mostly unmeasured (a sensor cannot see inside), and stays where it was
// measured (a hollow part's inner wall); the one beside it stays even unmeasured (the far side
// of an object a single view saw). One that pokes through the surface goes too, and so does
// one that blisters out of it where only its contact with the surface was measured.
TEST(DeliveredMesh, AnInventedShellInsideTheSurfaceIsRemoved) {
  auto scene = [](float inner_mark, float beside_mark, const core::Vec3f& inner = core::Vec3f(0.2f, 0.1f, 0)) {
    core::TriangleMesh mesh = core::SphereMesh(24, 48);
    mesh.normals.clear();
    mesh.vertex_attributes.clear();
    core::ScalarAttribute mark{"filled", std::vector<float>(mesh.vertices.size(), 0.0f)};
    auto add = [&](const core::Vec3f& centre, float value) {
      const core::TriangleMesh small = core::SphereMesh(12, 24, 0.3);
      const auto base = static_cast<uint32_t>(mesh.vertices.size());
      for (const core::Vec3f& v : small.vertices) mesh.vertices.push_back(v + centre);
      for (const core::Triangle& t : small.faces) mesh.faces.push_back({t[0] + base, t[1] + base, t[2] + base});
      mark.values.resize(mesh.vertices.size(), value);
    };
    add(inner, inner_mark);
    add(core::Vec3f(2.5f, 0, 0), beside_mark);
    mesh.vertex_attributes.push_back(mark);
    return mesh;
  };
  core::TriangleMesh invented = scene(1, 1);
  const size_t sphere_faces = core::SphereMesh(24, 48).faces.size();
  const size_t small_faces = core::SphereMesh(12, 24).faces.size();
  EXPECT_EQ(RemoveInventedInnerShells(invented, invented.vertex_attributes[0].values), 1);
  EXPECT_EQ(invented.faces.size(), sphere_faces + small_faces);
  EXPECT_EQ(invented.vertex_attributes[0].values.size(), invented.vertices.size());
  // What is left is the unit sphere and the one beside it (centroid x > 2).
  uint32_t count = 0;
  (void)core::ComponentOfFaces(invented, count);
  EXPECT_EQ(count, 2u);
  for (const core::Vec3f& v : invented.vertices) EXPECT_TRUE(std::abs(v.norm() - 1) < 1e-4 || v.x() > 2);

  core::TriangleMesh measured = scene(0, 1);
  EXPECT_EQ(RemoveInventedInnerShells(measured, measured.vertex_attributes[0].values), 0);
  EXPECT_EQ(measured.faces.size(), sphere_faces + 2 * small_faces);

  // An inner shell that pokes through the surface around it (a quarter of its area outside,
  // its first face among them, as where two fits of the same points cross) still goes.
  core::TriangleMesh crossing = scene(1, 1, core::Vec3f(0.5f, 0.5f, 0.45f));
  size_t outside = 0;
  for (const core::Vec3f& v : crossing.vertices) outside += v.norm() > 1.0001f;
  ASSERT_GT(outside, 0u);
  EXPECT_GT(crossing.vertices[core::SphereMesh(24, 48).vertices.size()].norm(), 1.0f);
  EXPECT_EQ(RemoveInventedInnerShells(crossing, crossing.vertex_attributes[0].values), 1);
  EXPECT_EQ(crossing.faces.size(), sphere_faces + small_faces);

  // A blister mostly outside, measured only where it runs along the skin (a second fit of the
  // skin's points that closed outward), goes; the same blister measured on its far side (an
  // object whose unseen back was closed into the surface behind it) stays.
  auto blister = [&](bool measured_on_skin) {
    core::TriangleMesh mesh = scene(1, 1, core::Vec3f(0, 0, 1.05f));
    std::vector<float>& marks = mesh.vertex_attributes[0].values;
    for (size_t v = core::SphereMesh(24, 48).vertices.size(); v < marks.size(); ++v) {
      const float norm = mesh.vertices[v].norm();
      if (measured_on_skin ? norm < 1.0f : mesh.vertices[v].z() > 1.2f && norm < 2) marks[v] = 0;
    }
    return mesh;
  };
  core::TriangleMesh on_skin = blister(true);
  EXPECT_EQ(RemoveInventedInnerShells(on_skin, on_skin.vertex_attributes[0].values), 1);
  EXPECT_EQ(on_skin.faces.size(), sphere_faces + small_faces);
  core::TriangleMesh object = blister(false);
  EXPECT_EQ(RemoveInventedInnerShells(object, object.vertex_attributes[0].values), 0);
}

TEST(DeliveredMesh, ExplicitBitsAreKeptAsAsked) {
  core::LocalJobContext ctx;
  auto result = ReconstructSurface("iamls", *DefaultParams("iamls"), testing::SphereCloud(3000), ctx);
  ASSERT_TRUE(result.ok());
  Statistics statistics;
  ASSERT_TRUE(EncodeResultMesh(result->mesh, 12, &statistics).ok());
  EXPECT_EQ(Statistic(statistics, "delivered_position_bits"), 12);
}

TEST(DeliveredMesh, VerticesTheQuantizationJoinsAreMergedWithoutFolds) {
  // An exact cylinder whose caps lie on the grid: along its rims, vertices of different edges come
  // out a float step or two apart, which no quantization keeps apart; merged as they are, faces
  // folded onto one another (48 non-manifold edges once).
  const double r = 0.18, h = 0.3;
  auto root = csg::ParseCsg("cylinder(a=0,0,0 b=0,0,0.3 r=0.18)");
  ASSERT_TRUE(root.ok()) << root.status();
  auto function = csg::BuildCsg(*root, [](const std::string& id) -> absl::StatusOr<csg::Operand> {
    return absl::NotFoundError(core::StrCat("no job ", id));
  });
  ASSERT_TRUE(function.ok()) << function.status();
  csg::CsgParams params;
  params.cell_size = 0.002;
  core::LocalJobContext ctx;
  auto result = csg::ExtractCsg(**function, params, ctx);
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_TRUE(core::AnalyzeTopology(core::WeldByPosition(result->mesh)).watertight());
  Statistics statistics;
  auto bytes = EncodeResultMesh(result->mesh, /*position_bits=*/0, &statistics);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  EXPECT_GT(Statistic(statistics, "delivery_dropped_faces"), 0);  // The case arises here.
  auto decoded = io::DecodeDracoMesh(*bytes);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  const core::TriangleMesh welded = core::WeldByPosition(*decoded);
  const core::MeshTopology delivered = core::AnalyzeTopology(welded);
  EXPECT_EQ(delivered.boundary_edges, 0);
  EXPECT_EQ(delivered.non_manifold_edges, 0);
  EXPECT_EQ(delivered.components, 1);
  EXPECT_EQ(delivered.euler_characteristic(), 2);
  EXPECT_EQ(Statistic(statistics, "non_manifold_edges"), 0);
  EXPECT_NEAR(core::EnclosedVolume(welded), std::numbers::pi * r * r * h, 1e-4 * std::numbers::pi * r * r * h);
}

}  // namespace
}  // namespace lsqsurf::jobs
