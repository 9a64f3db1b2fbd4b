// worker/core/mesh_metrics.h — topology and volume checks of triangle meshes.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "worker/core/geometry.h"

namespace lsqsurf::core {

// splitmix64's finaliser: a bijective mix, so distinct keys get unrelated hashes.
inline uint64_t Mix64(uint64_t x) {
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

// A face's share of hash(a→b) − hash(b→a) over the directed edges of a mesh. The mesh's sum is 0
// exactly when every edge is matched by its reverse (no border, neighbours wound alike), unless
// 64-bit hashes collide: a closedness test in one pass and no memory.
inline uint64_t UnmatchedEdgeSum(const Triangle& f) {
  auto edge = [](uint32_t from, uint32_t to) { return Mix64((uint64_t{from} << 32) | to); };
  return edge(f[0], f[1]) - edge(f[1], f[0]) + edge(f[1], f[2]) - edge(f[2], f[1]) + edge(f[2], f[0]) -
         edge(f[0], f[2]);
}

struct MeshTopology {
  int64_t vertices = 0;  // Vertices referenced by at least one face.
  int64_t edges = 0;     // Distinct undirected edges.
  int64_t faces = 0;
  int64_t boundary_edges = 0;      // Edges with exactly one incident face.
  int64_t non_manifold_edges = 0;  // Edges with three or more incident faces.
  int64_t misoriented_edges = 0;   // Two-face edges traversed in the same direction by both.
  int64_t degenerate_faces = 0;    // Faces that repeat a vertex index.
  int64_t components = 0;          // Face-connected components.
  // AnalyzeTopology's only (TopologyAccumulator leaves them 0):
  int64_t boundary_loops = 0;     // Connected pieces of the boundary edges (a pinched pair counts once).
  int64_t closed_components = 0;  // Components without a boundary edge.

  int64_t euler_characteristic() const { return vertices - edges + faces; }
  // Closed and edge-manifold: every edge has exactly two faces.
  bool watertight() const { return boundary_edges == 0 && non_manifold_edges == 0 && faces > 0; }
  bool consistently_oriented() const { return misoriented_edges == 0; }
};

// O(F log F). Works on any index soup; out-of-range indices are a broken invariant (asserted).
MeshTopology AnalyzeTopology(const TriangleMesh& mesh);

// The topology of a mesh seen a face at a time, as a mesh delivered in parts is (never whole):
// an edge is held only until its second face comes, so that memory follows the open seams
// between the faces seen and those to come, plus 4 bytes a vertex for the components. Differs from
// AnalyzeTopology in two ways: an edge with a third face counts as a boundary edge (one with four
// goes unseen), and components are joined through shared vertices, not only shared edges.
class TopologyAccumulator {
 public:
  // Vertex numbers of the whole mesh, below 2^32.
  void AddFace(int64_t a, int64_t b, int64_t c);
  // vertices, edges, faces, boundary_edges, misoriented_edges, degenerate_faces and components.
  MeshTopology Result();

 private:
  uint32_t Root(uint32_t v);
  std::vector<uint32_t> parent_;              // Union-find over the vertices; UINT32_MAX: not used yet.
  absl::flat_hash_map<uint64_t, bool> open_;  // (lo << 32 | hi) -> its face went lo to hi.
  int64_t faces_ = 0, closed_ = 0, misoriented_ = 0, degenerate_ = 0;
};

// The mesh with vertices at exactly the same position merged into one (as STL export and most
// tools do); faces keep their order and may become degenerate. Normals and attributes are
// dropped. O(V log V).
TriangleMesh WeldByPosition(const TriangleMesh& mesh);

// Merges the vertices at exactly the same position into the first of them (its normal and
// attributes stay), drops the faces that collapse, lets faces on the same three vertices with
// opposite orientations cancel (a pair encloses nothing; one of any rest stays), and drops the
// vertices no face uses. What a delivery whose
// quantization puts distinct vertices together must do to stay manifold. Returns the faces
// dropped. O(V log V + F log F).
int64_t MergeCoincidentVertices(TriangleMesh& mesh);

// Removes the components (faces connected through shared vertices) whose bounding-box diagonal
// is below `min_diagonal`, and the vertices only they used; the others keep their order, normals
// and attributes. Returns the components removed. O(V + F).
int64_t RemoveSmallComponents(TriangleMesh& mesh, double min_diagonal);

// Per face, the label (0 .. `count` − 1, in order of first face) of its component: faces
// connected through vertices at one position, so that a crease's split copies do not cut a
// surface in two. O(V log V + F).
std::vector<uint32_t> ComponentOfFaces(const TriangleMesh& mesh, uint32_t& count);

// The generalized winding number at each of `probes` of the faces flagged in `faces` (the sum of
// their solid angles over 4π): 1 inside a closed outward-facing surface, 0 outside, about ½ on a
// gap's border. The same on every run (summed in fixed blocks, in order). O(F · probes), in
// parallel.
std::vector<double> WindingNumbers(const TriangleMesh& mesh, std::span<const char> faces,
                                   std::span<const Vec3d> probes);

// Removes the faces flagged in `drop` and the vertices only they used; the others keep their
// order, normals and attributes. O(V + F).
void RemoveFaces(TriangleMesh& mesh, std::span<const char> drop);

// One flag per face: 1 where the face's component (faces connected through shared vertices) has a
// bounding box for which `pick` holds. Sets `picked` to the number of such components. O(V + F).
std::vector<char> FacesOfComponents(const TriangleMesh& mesh, const std::function<bool(const Box3&)>& pick,
                                    int64_t& picked);

// Vertex → incident faces as compressed rows for the vertices from `first` on: the faces of v are
// incident[start[v − first] .. start[v − first + 1]), in face order. O(V + F).
void IncidentFaces(const TriangleMesh& mesh, std::vector<uint32_t>& start, std::vector<uint32_t>& incident,
                   uint32_t first = 0);

// Number of distinct vertex positions.
int64_t CountDistinctPositions(const std::vector<Vec3f>& positions);

// Signed volume enclosed by a closed mesh (divergence theorem); positive when faces are
// oriented outward. Meaningless for open meshes.
double EnclosedVolume(const TriangleMesh& mesh);

// Total surface area.
double SurfaceArea(const TriangleMesh& mesh);

// The area of one face of `mesh`, in double precision.
double FaceArea(const TriangleMesh& mesh, const Triangle& face);

// The shape of the triangles: their smallest angles and aspect ratios (longest edge × perimeter /
// (4√3 × area): 1 for an equilateral triangle, infinite for a degenerate one).
struct TriangleQuality {
  static constexpr int kBinDegrees = 5;
  std::array<int64_t, 12> min_angle_histogram{};  // Faces whose smallest angle is in [5k, 5k + 5) degrees.
  double min_angle_p1 = 0;                        // 1st percentile of the smallest angle, degrees.
  double min_angle_median = 0;
  double aspect_ratio_p99 = 0;  // 99th percentile.
};
TriangleQuality MeasureTriangleQuality(const TriangleMesh& mesh);

}  // namespace lsqsurf::core
