#include "worker/core/mesh_metrics.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <numeric>
#include <random>
#include <tuple>
#include <utility>

#include "worker/core/sampling.h"
#include "worker/core/sphere_mesh.h"
#include "worker/core/surface_distance.h"

namespace lsqsurf::core {
namespace {

// Unit cube [0,1]^3 with outward faces.
TriangleMesh Cube(const Vec3f& offset = Vec3f::Zero(), float scale = 1.0f) {
  TriangleMesh m;
  for (int i = 0; i < 8; ++i) {
    m.vertices.push_back(offset + scale * Vec3f(static_cast<float>(i & 1), static_cast<float>((i >> 1) & 1),
                                                static_cast<float>((i >> 2) & 1)));
  }
  m.faces = {{0, 2, 1}, {1, 2, 3}, {4, 5, 6}, {5, 7, 6}, {0, 1, 4}, {1, 5, 4},
             {2, 6, 3}, {3, 6, 7}, {0, 4, 2}, {2, 4, 6}, {1, 3, 5}, {3, 7, 5}};
  return m;
}

TEST(MeshMetrics, CubeIsAClosedOrientedSphereTopology) {
  const TriangleMesh cube = Cube();
  const MeshTopology t = AnalyzeTopology(cube);
  EXPECT_TRUE(t.watertight());
  EXPECT_TRUE(t.consistently_oriented());
  EXPECT_EQ(t.euler_characteristic(), 2);
  EXPECT_EQ(t.components, 1);
  EXPECT_NEAR(EnclosedVolume(cube), 1.0, 1e-9);
  EXPECT_NEAR(SurfaceArea(cube), 6.0, 1e-9);
}

TEST(MeshMetrics, DetectsBoundaryFlipsAndNonManifoldEdges) {
  TriangleMesh open = Cube();
  open.faces.pop_back();
  EXPECT_EQ(AnalyzeTopology(open).boundary_edges, 3);
  TriangleMesh flipped = Cube();
  std::swap(flipped.faces[0][0], flipped.faces[0][1]);
  EXPECT_EQ(AnalyzeTopology(flipped).misoriented_edges, 3);
  TriangleMesh fin = Cube();
  fin.vertices.emplace_back(-1, -1, 0);
  fin.faces.push_back({0, 1, 8});
  EXPECT_EQ(AnalyzeTopology(fin).non_manifold_edges, 1);
}

// Boundary loops and closed components: a cube without its top is a disc (one loop), without its
// top and bottom a tube (two loops, Euler characteristic 0: still no handle, 2C − χ − B = 0).
TEST(MeshMetrics, CountsBoundaryLoopsAndClosedComponents) {
  const TriangleMesh cube = Cube();
  EXPECT_EQ(AnalyzeTopology(cube).boundary_loops, 0);
  EXPECT_EQ(AnalyzeTopology(cube).closed_components, 1);
  TriangleMesh cup = Cube();
  cup.faces.erase(cup.faces.begin() + 2, cup.faces.begin() + 4);  // z = 1.
  const MeshTopology disc = AnalyzeTopology(cup);
  EXPECT_EQ(disc.boundary_loops, 1);
  EXPECT_EQ(disc.closed_components, 0);
  EXPECT_EQ(disc.euler_characteristic(), 1);
  TriangleMesh tube = cup;
  tube.faces.erase(tube.faces.begin(), tube.faces.begin() + 2);  // z = 0.
  const MeshTopology annulus = AnalyzeTopology(tube);
  EXPECT_EQ(annulus.boundary_loops, 2);
  EXPECT_EQ(2 * annulus.components - annulus.euler_characteristic() - annulus.boundary_loops, 0);
  // The tube beside a closed cube: one closed component of two.
  const TriangleMesh second = Cube(Vec3f(3, 0, 0));
  for (const Triangle& f : second.faces) tube.faces.push_back({f[0] + 8, f[1] + 8, f[2] + 8});
  tube.vertices.insert(tube.vertices.end(), second.vertices.begin(), second.vertices.end());
  const MeshTopology both = AnalyzeTopology(tube);
  EXPECT_EQ(both.components, 2);
  EXPECT_EQ(both.closed_components, 1);
  EXPECT_EQ(both.boundary_loops, 2);
}

// Face by face, in any order, the accumulator agrees with the whole-mesh analysis.
MeshTopology Accumulated(const TriangleMesh& mesh, uint32_t seed) {
  std::vector<size_t> order(mesh.faces.size());
  std::iota(order.begin(), order.end(), 0);
  std::mt19937 random(seed);
  std::shuffle(order.begin(), order.end(), random);
  TopologyAccumulator accumulator;
  for (size_t f : order) accumulator.AddFace(mesh.faces[f][0], mesh.faces[f][1], mesh.faces[f][2]);
  return accumulator.Result();
}

TEST(MeshMetrics, TheAccumulatorAgreesWithTheWholeMeshFaceByFace) {
  TriangleMesh two = Cube();
  const TriangleMesh second = Cube(Vec3f(3, 0, 0));
  for (const Triangle& f : second.faces) two.faces.push_back({f[0] + 8, f[1] + 8, f[2] + 8});
  two.vertices.insert(two.vertices.end(), second.vertices.begin(), second.vertices.end());
  TriangleMesh open = Cube(), flipped = Cube();
  open.faces.pop_back();
  std::swap(flipped.faces[0][0], flipped.faces[0][1]);
  for (const TriangleMesh* mesh : {&two, &open, &flipped}) {
    const MeshTopology whole = AnalyzeTopology(*mesh);
    for (uint32_t seed : {1u, 2u, 3u}) {
      const MeshTopology seen = Accumulated(*mesh, seed);
      EXPECT_EQ(seen.vertices, whole.vertices);
      EXPECT_EQ(seen.edges, whole.edges);
      EXPECT_EQ(seen.faces, whole.faces);
      EXPECT_EQ(seen.boundary_edges, whole.boundary_edges);
      EXPECT_EQ(seen.misoriented_edges, whole.misoriented_edges);
      EXPECT_EQ(seen.degenerate_faces, whole.degenerate_faces);
      EXPECT_EQ(seen.components, whole.components);
    }
  }
  EXPECT_EQ(Accumulated(two, 1).components, 2);
  EXPECT_EQ(Accumulated(two, 1).euler_characteristic(), 4);
  // A third face on an edge leaves it open: not closed, as the whole analysis says.
  TriangleMesh fin = Cube();
  fin.vertices.emplace_back(-1, -1, 0);
  fin.faces.push_back({0, 1, 8});
  EXPECT_FALSE(Accumulated(fin, 1).watertight());
  TopologyAccumulator degenerate;
  degenerate.AddFace(0, 0, 1);
  degenerate.AddFace(4, 5, 5);
  EXPECT_EQ(degenerate.Result().degenerate_faces, 2);
}

TEST(MeshMetrics, MergingCoincidentVerticesRemovesFoldsAndKeepsTheSolid) {
  TriangleMesh cube = Cube();
  cube.normals.assign(cube.vertices.size(), Vec3f::UnitZ());
  cube.vertex_attributes.push_back({"id", {0, 1, 2, 3, 4, 5, 6, 7}});
  // Vertex 8 sits on vertex 3 and takes its place in one face, with a face collapsing between
  // them; vertex 9 sits on vertex 7 with two faces that fold onto the face 5–7–6.
  for (const uint32_t twin : {3u, 7u}) {
    cube.vertices.push_back(cube.vertices[twin]);
    cube.normals.push_back(Vec3f::UnitX());
    cube.vertex_attributes[0].values.push_back(static_cast<float>(10 + twin));
  }
  cube.faces[1] = {1, 2, 8};
  cube.faces.push_back({2, 8, 3});
  cube.faces.push_back({5, 9, 6});
  cube.faces.push_back({9, 5, 6});
  EXPECT_GT(AnalyzeTopology(WeldByPosition(cube)).non_manifold_edges, 0);
  EXPECT_EQ(MergeCoincidentVertices(cube), 3);
  const MeshTopology t = AnalyzeTopology(cube);
  EXPECT_TRUE(t.watertight());
  EXPECT_TRUE(t.consistently_oriented());
  EXPECT_EQ(t.euler_characteristic(), 2);
  EXPECT_EQ(cube.vertices.size(), 8u);
  EXPECT_NEAR(EnclosedVolume(cube), 1.0, 1e-9);
  // The first vertex at each position stays, with its normal and attributes.
  EXPECT_EQ(cube.vertex_attributes[0].values, (std::vector<float>{0, 1, 2, 3, 4, 5, 6, 7}));
  EXPECT_EQ(cube.normals[3], Vec3f::UnitZ());
}

// A unit cube, a cube of edge 0.1 beside it and one of edge 0.5: with a threshold between their
// diagonals (0.17, 0.87, 1.73) the small one goes with its vertices, and the rest keep their
// positions, normals and attributes.
TEST(MeshMetrics, RemovesComponentsSmallerThanADiagonal) {
  TriangleMesh mesh = Cube();
  for (const auto& [offset, scale] : {std::pair{Vec3f(3, 0, 0), 0.1f}, std::pair{Vec3f(5, 0, 0), 0.5f}}) {
    const TriangleMesh part = Cube(offset, scale);
    const auto base = static_cast<uint32_t>(mesh.vertices.size());
    mesh.vertices.insert(mesh.vertices.end(), part.vertices.begin(), part.vertices.end());
    for (Triangle t : part.faces) mesh.faces.push_back({t[0] + base, t[1] + base, t[2] + base});
  }
  std::vector<float> ids(mesh.vertices.size());
  std::iota(ids.begin(), ids.end(), 0.0f);
  mesh.vertex_attributes.push_back({"id", ids});
  mesh.normals.assign(mesh.vertices.size(), Vec3f::UnitY());
  EXPECT_EQ(AnalyzeTopology(mesh).components, 3);
  EXPECT_EQ(RemoveSmallComponents(mesh, 0.05), 0);
  EXPECT_EQ(RemoveSmallComponents(mesh, 0.5), 1);
  const MeshTopology t = AnalyzeTopology(mesh);
  EXPECT_EQ(t.components, 2);
  EXPECT_TRUE(t.watertight());
  ASSERT_EQ(mesh.vertices.size(), 16u);
  EXPECT_NEAR(EnclosedVolume(mesh), 1.0 + 0.125, 1e-6);
  for (size_t v = 0; v < 16; ++v) EXPECT_EQ(mesh.vertex_attributes[0].values[v], v < 8 ? v : v + 8);
  EXPECT_EQ(mesh.normals.size(), 16u);
  EXPECT_EQ(RemoveSmallComponents(mesh, 10), 2);
  EXPECT_TRUE(mesh.vertices.empty() && mesh.faces.empty());
}

TEST(SurfaceDistance, MeasuresAKnownOffset) {
  const TriangleMesh a = Cube();
  LocalJobContext ctx;
  CompareParams p;
  p.samples = 20000;
  auto same = CompareMeshes(a, a, p, ctx);
  ASSERT_TRUE(same.ok());
  EXPECT_LT(same->chamfer, 1e-7);
  EXPECT_NEAR(same->normal_consistency, 1.0, 1e-6);
  // A cube grown by 0.1 on every side (centred): every point is 0.1 or more from the other.
  const TriangleMesh b = Cube(Vec3f::Constant(-0.1f), 1.2f);
  auto moved = CompareMeshes(a, b, p, ctx);
  ASSERT_TRUE(moved.ok());
  const double diag = std::sqrt(3.0);
  EXPECT_NEAR(moved->mean_ref_to_cand * diag, 0.1, 1e-3);  // Faces are parallel at distance 0.1.
  EXPECT_GT(moved->hausdorff * diag, 0.15);                // Near the corners.
  EXPECT_NEAR(moved->hausdorff_with_vertices * diag, 0.1 * std::sqrt(3.0), 1e-6);  // Corner to corner.
  EXPECT_NEAR(moved->far_fraction, 1.0, 1e-9);
}

// A square pyramid (base [-1, 1]² at z = 0, apex at z = 2) and the same with its tip cut off at
// height 2 − h: the cut takes a share of the surface that no area sample lands in, yet the apex
// is h from the cap, the farthest any point of either surface is from the other.
TriangleMesh Pyramid(double cut) {
  TriangleMesh m;
  m.vertices = {{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
  m.faces = {{0, 2, 1}, {0, 3, 2}};
  if (cut == 0) {
    m.vertices.push_back({0, 0, 2});
    for (uint32_t i = 0; i < 4; ++i) m.faces.push_back({i, (i + 1) % 4, 4});
    return m;
  }
  const auto half = static_cast<float>(cut / 2), top = static_cast<float>(2 - cut);
  for (const auto& [x, y] : {std::pair{-1, -1}, {1, -1}, {1, 1}, {-1, 1}}) {
    m.vertices.push_back({half * static_cast<float>(x), half * static_cast<float>(y), top});
  }
  m.faces.push_back({4, 5, 6});
  m.faces.push_back({4, 6, 7});
  for (uint32_t i = 0; i < 4; ++i) {
    const uint32_t j = (i + 1) % 4;
    m.faces.push_back({i, j, j + 4});
    m.faces.push_back({i, j + 4, i + 4});
  }
  return m;
}

TEST(SurfaceDistance, TheVerticesFindACornerTheAreaSamplesMiss) {
  const TriangleMesh apex = Pyramid(0), cut = Pyramid(0.002);
  ASSERT_TRUE(AnalyzeTopology(apex).watertight());
  ASSERT_TRUE(AnalyzeTopology(cut).watertight());
  EXPECT_NEAR(EnclosedVolume(apex), 8.0 / 3.0, 1e-5);  // Both wound outwards.
  EXPECT_NEAR(EnclosedVolume(cut), 8.0 / 3.0, 1e-5);
  LocalJobContext ctx;
  CompareParams p;
  p.samples = 2000;
  auto result = CompareMeshes(apex, cut, p, ctx);
  ASSERT_TRUE(result.ok());
  const double diag = Diagonal(BoundingBox(apex.vertices));
  EXPECT_NEAR(result->hausdorff_with_vertices * diag, 0.002, 1e-6);
  EXPECT_LT(result->hausdorff * diag, 0.001);  // Area samples: none near the tip.
}

TEST(SurfaceDistance, ClosestPointIsExact) {
  const TriangleMesh cube = Cube();
  TriangleTree tree(cube);
  const auto hit = tree.Closest(Vec3d(0.5, 0.5, 3.0));
  EXPECT_NEAR(std::sqrt(hit.distance2), 2.0, 1e-12);
  EXPECT_NEAR(hit.point.z(), 1.0, 1e-12);
  const auto corner = tree.Closest(Vec3d(2, 2, 2));
  EXPECT_NEAR(corner.distance2, 3.0, 1e-12);
}

TEST(Sampling, IsUniformByArea) {
  TriangleMesh two;  // Two triangles, one with 3 times the area of the other.
  two.vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {5, 0, 0}, {8, 0, 0}, {5, 1, 0}};
  two.faces = {{0, 1, 2}, {3, 4, 5}};
  const auto samples = SampleSurface(two, 40000, 3);
  double big = 0;
  for (const auto& s : samples) big += s.face == 1;
  EXPECT_NEAR(big / 40000.0, 0.75, 0.01);
}

// `mesh` with its vertices renumbered at random (normals and attributes with them), its faces
// shuffled and each rotated by a random turn.
TriangleMesh Renumbered(const TriangleMesh& mesh, uint32_t seed) {
  std::mt19937 random(seed);
  std::vector<uint32_t> to(mesh.vertices.size());
  std::iota(to.begin(), to.end(), 0u);
  std::shuffle(to.begin(), to.end(), random);
  TriangleMesh m = mesh;
  for (size_t v = 0; v < to.size(); ++v) {
    m.vertices[to[v]] = mesh.vertices[v];
    if (!mesh.normals.empty()) m.normals[to[v]] = mesh.normals[v];
    for (size_t a = 0; a < mesh.vertex_attributes.size(); ++a) {
      m.vertex_attributes[a].values[to[v]] = mesh.vertex_attributes[a].values[v];
    }
  }
  for (Triangle& t : m.faces) {
    t = {to[t[0]], to[t[1]], to[t[2]]};
    std::rotate(t.begin(), t.begin() + random() % 3, t.end());
  }
  std::shuffle(m.faces.begin(), m.faces.end(), random);
  return m;
}

// Two numberings of one sphere (vertices shuffled, faces shuffled and rotated) sort to the same
// mesh, with each attribute value still on its vertex and the volume's sign (orientation) kept.
TEST(SortMeshByPosition, GivesOneOrderForEveryNumberingOfASurface) {
  TriangleMesh sphere = SphereMesh(12, 24);
  ScalarAttribute height{"height", {}};
  for (const Vec3f& v : sphere.vertices) height.values.push_back(v.z());
  sphere.vertex_attributes.push_back(height);
  TriangleMesh a = Renumbered(sphere, 1), b = Renumbered(sphere, 2);
  ASSERT_NE(a.vertices, b.vertices);
  SortMeshByPosition(a);
  SortMeshByPosition(b);
  EXPECT_EQ(a.vertices, b.vertices);
  EXPECT_EQ(a.faces, b.faces);
  EXPECT_EQ(a.vertex_attributes[0].values, b.vertex_attributes[0].values);
  for (size_t v = 0; v < a.vertices.size(); ++v) EXPECT_EQ(a.vertex_attributes[0].values[v], a.vertices[v].z());
  EXPECT_TRUE(std::is_sorted(a.vertices.begin(), a.vertices.end(), [](const Vec3f& p, const Vec3f& q) {
    return std::tie(p.x(), p.y(), p.z()) < std::tie(q.x(), q.y(), q.z());
  }));
  EXPECT_NEAR(EnclosedVolume(a), EnclosedVolume(sphere), 1e-9 * std::abs(EnclosedVolume(sphere)));
  EXPECT_GT(EnclosedVolume(sphere), 0);
}

// A cube as sharp-feature extraction writes it: each face has its own four corners with the
// face's normal, so every corner position holds three vertices. Their order comes from the
// surface too: any numbering sorts to one mesh, and each copy keeps its own face's normal.
TEST(SortMeshByPosition, OrdersCoincidentVerticesByTheSurfaceAroundThem) {
  TriangleMesh cube;
  for (int axis = 0; axis < 3; ++axis) {
    for (int side : {-1, 1}) {
      Vec3f normal = Vec3f::Zero();
      normal[axis] = static_cast<float>(side);
      const int u = (axis + 1) % 3, w = (axis + 2) % 3;
      const auto base = static_cast<uint32_t>(cube.vertices.size());
      for (auto [du, dw] : {std::pair{-1, -1}, {1, -1}, {1, 1}, {-1, 1}}) {
        Vec3f p = normal;
        p[u] = static_cast<float>(du);
        p[w] = static_cast<float>(dw);
        cube.vertices.push_back(p);
        cube.normals.push_back(normal);
      }
      // Outward when u, w, axis are right-handed; flipped on the negative side.
      if (side > 0) {
        cube.faces.push_back({base, base + 1, base + 2});
        cube.faces.push_back({base, base + 2, base + 3});
      } else {
        cube.faces.push_back({base, base + 2, base + 1});
        cube.faces.push_back({base, base + 3, base + 2});
      }
    }
  }
  ASSERT_NEAR(EnclosedVolume(WeldByPosition(cube)), 8.0, 1e-9);
  TriangleMesh a = Renumbered(cube, 3), b = Renumbered(cube, 4);
  SortMeshByPosition(a);
  SortMeshByPosition(b);
  EXPECT_EQ(a.vertices, b.vertices);
  EXPECT_EQ(a.normals, b.normals);
  EXPECT_EQ(a.faces, b.faces);
  for (const Triangle& t : a.faces) {
    const Vec3f face_normal =
        (a.vertices[t[1]] - a.vertices[t[0]]).cross(a.vertices[t[2]] - a.vertices[t[0]]).normalized();
    for (uint32_t v : t) EXPECT_EQ(a.normals[v], face_normal);
  }
}

// The winding numbers of a closed sphere are 1 inside and 0 outside (the solid angles sum to 4π
// or cancel), each probe its own; of its upper half alone, ½ at the centre. Components are counted by position, so a
// sphere whose faces each have their own corners is still one.
TEST(WindingNumbers, AreOneInsideAClosedSurfaceAndZeroOutside) {
  const TriangleMesh sphere = SphereMesh(24, 48);
  const std::vector<char> all(sphere.faces.size(), 1);
  const std::vector<Vec3d> probes = {Vec3d(0.3, -0.2, 0.1), Vec3d(1.5, 0.2, 0), Vec3d(0, 0, -0.9)};
  const std::vector<double> whole = WindingNumbers(sphere, all, probes);
  ASSERT_EQ(whole.size(), 3u);
  EXPECT_NEAR(whole[0], 1.0, 1e-9);
  EXPECT_NEAR(whole[1], 0.0, 1e-9);
  EXPECT_NEAR(whole[2], 1.0, 1e-9);
  std::vector<char> upper(sphere.faces.size(), 0);
  for (size_t f = 0; f < sphere.faces.size(); ++f) {
    const Triangle& t = sphere.faces[f];
    upper[f] = sphere.vertices[t[0]].z() + sphere.vertices[t[1]].z() + sphere.vertices[t[2]].z() > 0;
  }
  const std::vector<Vec3d> centre = {Vec3d::Zero()};
  EXPECT_NEAR(WindingNumbers(sphere, upper, centre)[0], 0.5, 1e-9);
  EXPECT_TRUE(WindingNumbers(sphere, upper, {}).empty());

  TriangleMesh split;
  for (const Triangle& t : sphere.faces) {
    const auto base = static_cast<uint32_t>(split.vertices.size());
    for (uint32_t v : t) split.vertices.push_back(sphere.vertices[v]);
    split.faces.push_back({base, base + 1, base + 2});
  }
  uint32_t count = 0;
  const std::vector<uint32_t> label = ComponentOfFaces(split, count);
  EXPECT_EQ(count, 1u);
  EXPECT_TRUE(std::ranges::all_of(label, [](uint32_t l) { return l == 0; }));
}

}  // namespace
}  // namespace lsqsurf::core
