// Closing small holes: slits and single faces cut from a closed sphere close again with the
// sphere's topology and nearly its volume, also where two touch at a vertex or a border touches
// itself; long borders and three holes at one vertex stay.
#include "worker/extract/holes.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <functional>
#include <numbers>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::extract::internal {
namespace {

using core::AnalyzeTopology;
using core::MeshTopology;
using core::TriangleMesh;

// A closed unit sphere marched on a grid from its exact distance field.
TriangleMesh Sphere() {
  const testing::SphereField field(1.0);
  core::LocalJobContext ctx;
  IsosurfaceParams p;
  p.cell_size = 0.1;
  auto r = ExtractIsosurface(field, testing::SphereCloud(2000).positions, p, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? r->mesh : TriangleMesh{};
}

// The mesh without the faces whose centroid `cut` picks.
TriangleMesh Without(TriangleMesh mesh, const std::function<bool(const core::Vec3f&)>& cut) {
  std::erase_if(mesh.faces, [&](const core::Triangle& f) {
    return cut((mesh.vertices[f[0]] + mesh.vertices[f[1]] + mesh.vertices[f[2]]) / 3.0f);
  });
  return mesh;
}

TEST(FillSmallHoles, ASlitAndACapCloseWithTheSpheresTopology) {
  const TriangleMesh sphere = Sphere();
  ASSERT_TRUE(AnalyzeTopology(sphere).watertight());
  TriangleMesh cut = Without(sphere, [](const core::Vec3f& c) {
    const bool slit = c.x() > 0.9f && std::abs(c.z()) < 0.05f && std::abs(c.y()) < 0.25f;
    const bool cap = c.z() > 0.985f;
    return slit || cap;
  });
  const MeshTopology before = AnalyzeTopology(cut);
  ASSERT_EQ(before.boundary_loops, 2);
  const size_t removed = sphere.faces.size() - cut.faces.size();
  ASSERT_GE(removed, 6u);

  EXPECT_EQ(FillSmallHoles(cut, 32), 2);
  const MeshTopology after = AnalyzeTopology(cut);
  EXPECT_TRUE(after.watertight());
  EXPECT_TRUE(after.consistently_oriented());
  EXPECT_EQ(after.euler_characteristic(), 2);
  EXPECT_EQ(after.non_manifold_edges, 0);
  // No vertex is added: the fill spans the border with two triangles fewer than it has edges.
  EXPECT_EQ(cut.vertices.size(), sphere.vertices.size());
  // Flat patches over small holes of a unit sphere lose little volume.
  EXPECT_NEAR(core::EnclosedVolume(cut) / core::EnclosedVolume(sphere), 1.0, 2e-3);
}

TEST(FillSmallHoles, LongBordersStayOpen) {
  TriangleMesh cut = Without(Sphere(), [](const core::Vec3f& c) { return c.z() > 0.5f; });
  const size_t faces = cut.faces.size();
  EXPECT_EQ(FillSmallHoles(cut, 32), 0);  // The border has about 2π · 0.87 / 0.07 edges.
  EXPECT_EQ(cut.faces.size(), faces);
}

// The faces around one vertex that share no edge with each other, up to `count` of them.
std::vector<size_t> ApartAround(const TriangleMesh& mesh, uint32_t v, size_t count) {
  auto share_edge = [&](size_t a, size_t b) {
    int common = 0;
    for (uint32_t x : mesh.faces[a]) common += std::ranges::find(mesh.faces[b], x) != mesh.faces[b].end();
    return common == 2;
  };
  std::vector<size_t> apart;
  for (size_t f = 0; f < mesh.faces.size() && apart.size() < count; ++f) {
    if (std::ranges::find(mesh.faces[f], v) == mesh.faces[f].end()) continue;
    if (std::ranges::none_of(apart, [&](size_t g) { return share_edge(f, g); })) apart.push_back(f);
  }
  return apart;
}

TriangleMesh WithoutFaces(TriangleMesh mesh, std::vector<size_t> faces) {
  std::ranges::sort(faces, std::greater<>());
  for (size_t f : faces) mesh.faces.erase(mesh.faces.begin() + static_cast<std::ptrdiff_t>(f));
  return mesh;
}

TEST(FillSmallHoles, MissingFacesThatTouchAtAVertexComeBackUnlessThreeDo) {
  const TriangleMesh sphere = Sphere();
  // A vertex where three faces apart can go: its fan has at least six.
  uint32_t v = 0;
  std::vector<size_t> apart;
  for (const core::Triangle& f : sphere.faces) {
    apart = ApartAround(sphere, f[0], 3);
    v = f[0];
    if (apart.size() == 3) break;
  }
  ASSERT_EQ(apart.size(), 3u);

  TriangleMesh one = WithoutFaces(sphere, {apart[0]});
  EXPECT_EQ(FillSmallHoles(one, 32), 1);
  EXPECT_TRUE(AnalyzeTopology(one).watertight());

  // Two holes that meet at v: each loop takes the way across its own gap between v's two fans
  // of faces, so both close and v is manifold again.
  TriangleMesh two = WithoutFaces(sphere, {apart[0], apart[1]});
  ASSERT_EQ(AnalyzeTopology(two).boundary_edges, 6);
  EXPECT_EQ(FillSmallHoles(two, 32), 2);
  const MeshTopology closed = AnalyzeTopology(two);
  EXPECT_TRUE(closed.watertight());
  EXPECT_TRUE(closed.consistently_oriented());
  EXPECT_EQ(closed.euler_characteristic(), 2);
  EXPECT_EQ(closed.non_manifold_edges, 0);
  // The two triangles that were cut out, each with its own three corners.
  for (size_t f : {apart[0], apart[1]}) {
    core::Triangle cut = sphere.faces[f];
    std::ranges::sort(cut);
    EXPECT_TRUE(std::ranges::any_of(two.faces, [&](core::Triangle t) { return std::ranges::sort(t), t == cut; }))
        << "face " << f << " around vertex " << v;
  }

  // Three fans at v: which gap each border edge faces is not clear from the pairs alone.
  TriangleMesh three = WithoutFaces(sphere, apart);
  EXPECT_EQ(FillSmallHoles(three, 32), 0);
  EXPECT_EQ(AnalyzeTopology(three).boundary_edges, 9);
}

// Whether the faces around v form one fan that closes on itself (v is manifold inside).
bool OneClosedFan(const TriangleMesh& mesh, uint32_t v) {
  std::vector<core::Triangle> fan;
  for (const core::Triangle& f : mesh.faces) {
    if (std::ranges::find(f, v) != f.end()) fan.push_back(f);
  }
  auto next_of = [&](const core::Triangle& f) {  // The vertex after v in f.
    return f[0] == v ? f[1] : (f[1] == v ? f[2] : f[0]);
  };
  auto previous_of = [&](const core::Triangle& f) { return f[0] == v ? f[2] : (f[1] == v ? f[0] : f[1]); };
  // Around v, each face's edge (v, next) is the next face's edge (previous, v).
  size_t at = 0;
  for (size_t step = 0; step < fan.size(); ++step) {
    const auto found =
        std::ranges::find_if(fan, [&](const core::Triangle& g) { return previous_of(g) == next_of(fan[at]); });
    if (found == fan.end()) return false;
    at = static_cast<size_t>(found - fan.begin());
    if (at == 0) return step + 1 == fan.size();
  }
  return false;
}

TEST(FillSmallHoles, AHoleWhoseBorderTouchesItselfClosesAsOneDisk) {
  // A 5 × 5 grid of unit squares, two triangles each. Seven of the eight squares around the middle
  // one go; the eighth stays, so the middle square hangs at the one corner P it shares with it:
  // the hole's border passes P twice.
  constexpr uint32_t kSide = 6;
  TriangleMesh grid;
  for (uint32_t y = 0; y < kSide; ++y) {
    for (uint32_t x = 0; x < kSide; ++x) grid.vertices.emplace_back(static_cast<float>(x), static_cast<float>(y), 0.0f);
  }
  auto id = [&](uint32_t x, uint32_t y) { return y * kSide + x; };
  for (uint32_t y = 0; y + 1 < kSide; ++y) {
    for (uint32_t x = 0; x + 1 < kSide; ++x) {
      const bool ring = x >= 1 && x <= 3 && y >= 1 && y <= 3 && !(x == 2 && y == 2) && !(x == 1 && y == 1);
      if (ring) continue;
      grid.faces.push_back({id(x, y), id(x + 1, y), id(x + 1, y + 1)});
      grid.faces.push_back({id(x, y), id(x + 1, y + 1), id(x, y + 1)});
    }
  }
  const uint32_t pinch = id(2, 2);
  ASSERT_FALSE(OneClosedFan(grid, pinch));
  const MeshTopology before = AnalyzeTopology(grid);
  ASSERT_EQ(before.boundary_edges, 20 + 16);  // The grid's rim and the hole's border.

  EXPECT_EQ(FillSmallHoles(grid, 16), 1);  // The rim, 20 edges, is beyond the limit.
  const MeshTopology after = AnalyzeTopology(grid);
  EXPECT_EQ(after.boundary_edges, 20);
  EXPECT_EQ(after.non_manifold_edges, 0);
  EXPECT_TRUE(after.consistently_oriented());
  EXPECT_EQ(after.degenerate_faces, 0);
  EXPECT_TRUE(OneClosedFan(grid, pinch));
}

TEST(CloseSmallHoles, ClosesAFinishedSurfacesHolesButTheOnesKeptOpen) {
  // Two single faces cut from opposite ends of the sphere; the one at +x is to stay open.
  IsosurfaceResult result;
  result.mesh = Without(Sphere(), [](const core::Vec3f& c) { return std::abs(c.x()) > 0.995f; });
  const MeshTopology before = AnalyzeTopology(result.mesh);
  ASSERT_EQ(before.boundary_loops, 2);
  result.trace.face_cells.assign(result.mesh.faces.size(), 1);
  result.trace.vertex_edges.assign(result.mesh.vertices.size(), 1);
  CloseSmallHoles(result, 32, [](const core::Vec3f& v) { return v.x() > 0.9f; });
  EXPECT_EQ(result.stats.filled_holes, 1);
  const MeshTopology after = AnalyzeTopology(result.mesh);
  EXPECT_EQ(after.boundary_loops, 1);
  EXPECT_EQ(after.non_manifold_edges, 0);
  // The trace no longer covers every face: it goes.
  EXPECT_TRUE(result.trace.face_cells.empty());
  EXPECT_TRUE(result.trace.vertex_edges.empty());
  CloseSmallHoles(result, 32);
  EXPECT_EQ(result.stats.filled_holes, 2);
  EXPECT_TRUE(AnalyzeTopology(result.mesh).watertight());
}

TEST(FillSmallHoles, ALoneTriangleIsNotDoubled) {
  TriangleMesh lone;
  lone.vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  lone.faces = {{0, 1, 2}};
  EXPECT_EQ(FillSmallHoles(lone, 32), 0);
  EXPECT_EQ(lone.faces.size(), 1u);
}

}  // namespace
}  // namespace lsqsurf::extract::internal
