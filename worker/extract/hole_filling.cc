#include "worker/extract/hole_filling.h"

#include <Eigen/Geometry>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <queue>
#include <tuple>
#include <vector>

#include "absl/container/btree_set.h"
#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/status.h"
#include "worker/extract/holes.h"

namespace lsqsurf::extract {
namespace {

using core::Triangle;
using core::Vec3f;

constexpr uint32_t kNoFace = std::numeric_limits<uint32_t>::max();
// Loops up to this long are triangulated directly (O(n³) in time, O(n²) in memory).
constexpr size_t kDirectEdges = 40;
constexpr int kFlipPasses = 4;
constexpr int kRelaxations = 3;
constexpr int kRefinements = 16;  // Split and flip rounds; each halves the longest edges.

uint64_t Undirected(uint32_t a, uint32_t b) { return a < b ? (uint64_t{a} << 32) | b : (uint64_t{b} << 32) | a; }

// Area, plus a penalty that keeps the triangulation away from slivers where a fatter choice
// exists: the straight chords of a cut would otherwise carry triangles of three nearly
// collinear vertices, which the fairing cannot open.
double FillingCost(const Vec3f& a, const Vec3f& b, const Vec3f& c) {
  const double area = internal::TriangleArea(a, b, c);
  const double squares = static_cast<double>((b - a).squaredNorm() + (c - b).squaredNorm() + (a - c).squaredNorm());
  if (squares <= 0) return 0;
  const double shape = 4 * std::numbers::sqrt3 * area / squares;  // 1 equilateral, 0 degenerate.
  return area + squares * std::max(0.0, 0.3 - shape);
}

// The faces of one hole's filling with their edges, refined and flipped in place.
class Patch {
 public:
  Patch(core::TriangleMesh& mesh, std::vector<Triangle> faces, const std::function<bool(uint32_t, uint32_t)>& is_edge)
      : mesh_(mesh), faces_(std::move(faces)), is_edge_(is_edge) {
    for (uint32_t f = 0; f < faces_.size(); ++f) {
      for (size_t s = 0; s < 3; ++s) Attach(faces_[f][s], faces_[f][(s + 1) % 3], f);
    }
  }

  // Splits each inner edge longer than `limit` at its middle, longest first, while fewer than
  // `max_vertices` are added; the edges the splits make wait for the next call (after a flip:
  // splitting them at once would keep the thin triangles of a fan thin, and split them on).
  // Returns the number of splits.
  size_t Refine(double limit, size_t max_vertices) {
    const size_t added_before = added_;
    const double limit2 = limit * limit;
    using Item = std::tuple<double, uint32_t, uint32_t>;
    std::priority_queue<Item> longest;
    auto offer = [&](uint32_t a, uint32_t b) {
      const double l2 = Length2(a, b);
      if (l2 > limit2 && Inner(a, b)) longest.emplace(l2, a, b);
    };
    for (const auto& [key, pair] : edges_) offer(static_cast<uint32_t>(key >> 32), static_cast<uint32_t>(key));
    while (!longest.empty() && added_ < max_vertices) {
      const auto [l2, a, b] = longest.top();
      longest.pop();
      if (!Inner(a, b)) continue;
      const auto [f1, f2] = FacesAlong(a, b);  // f1 runs a→b, f2 b→a.
      const uint32_t c = Third(f1, a, b), d = Third(f2, a, b);
      const auto m = static_cast<uint32_t>(mesh_.vertices.size());
      mesh_.vertices.push_back(0.5f * (mesh_.vertices[a] + mesh_.vertices[b]));
      ++added_;
      edges_.erase(Undirected(a, b));
      const auto f3 = static_cast<uint32_t>(faces_.size()), f4 = f3 + 1;
      faces_[f1] = {a, m, c};
      faces_.push_back({m, b, c});
      faces_[f2] = {b, m, d};
      faces_.push_back({m, a, d});
      Replace(b, c, f1, f3);
      Replace(a, d, f2, f4);
      Attach(a, m, f1), Attach(a, m, f4);
      Attach(m, b, f3), Attach(m, b, f2);
      Attach(m, c, f1), Attach(m, c, f3);
      Attach(m, d, f2), Attach(m, d, f4);
    }
    return added_ - added_before;
  }

  // Flips each inner edge whose opposite angles sum to more than π (towards a Delaunay mesh),
  // where the other diagonal is not an edge already.
  void Flip() {
    for (int pass = 0; pass < kFlipPasses; ++pass) {
      std::vector<uint64_t> keys;
      keys.reserve(edges_.size());
      for (const auto& [key, pair] : edges_) keys.push_back(key);
      std::ranges::sort(keys);  // The same mesh on every run (the map's order is seeded).
      int flipped = 0;
      for (uint64_t key : keys) {
        const auto a = static_cast<uint32_t>(key >> 32), b = static_cast<uint32_t>(key);
        if (!Inner(a, b)) continue;
        const auto [f1, f2] = FacesAlong(a, b);
        const uint32_t c = Third(f1, a, b), d = Third(f2, a, b);
        if (c == d || edges_.contains(Undirected(c, d)) || is_edge_(c, d)) continue;
        if (Angle(c, a, b) + Angle(d, a, b) <= std::numbers::pi + 1e-9) continue;
        edges_.erase(key);
        faces_[f1] = {a, d, c};
        faces_[f2] = {d, b, c};
        Replace(a, d, f2, f1);
        Replace(b, c, f1, f2);
        Attach(c, d, f1), Attach(c, d, f2);
        ++flipped;
      }
      if (flipped == 0) break;
    }
  }

  const std::vector<Triangle>& faces() const { return faces_; }

 private:
  void Attach(uint32_t a, uint32_t b, uint32_t face) {
    auto [it, fresh] = edges_.try_emplace(Undirected(a, b), std::array<uint32_t, 2>{face, kNoFace});
    if (!fresh && it->second[0] != face) it->second[1] = face;
  }
  void Replace(uint32_t a, uint32_t b, uint32_t from, uint32_t to) {
    auto& pair = edges_.at(Undirected(a, b));
    for (uint32_t& f : pair) f = f == from ? to : f;
  }
  bool Inner(uint32_t a, uint32_t b) const {
    const auto it = edges_.find(Undirected(a, b));
    return it != edges_.end() && it->second[1] != kNoFace;
  }
  bool Runs(uint32_t f, uint32_t a, uint32_t b) const {
    const Triangle& t = faces_[f];
    return (t[0] == a && t[1] == b) || (t[1] == a && t[2] == b) || (t[2] == a && t[0] == b);
  }
  std::pair<uint32_t, uint32_t> FacesAlong(uint32_t a, uint32_t b) const {
    const auto& pair = edges_.at(Undirected(a, b));
    return Runs(pair[0], a, b) ? std::pair{pair[0], pair[1]} : std::pair{pair[1], pair[0]};
  }
  uint32_t Third(uint32_t f, uint32_t a, uint32_t b) const {
    for (uint32_t v : faces_[f]) {
      if (v != a && v != b) return v;
    }
    return a;
  }
  double Length2(uint32_t a, uint32_t b) const {
    return static_cast<double>((mesh_.vertices[a] - mesh_.vertices[b]).squaredNorm());
  }
  // The angle at `apex` of the triangle it makes with a and b.
  double Angle(uint32_t apex, uint32_t a, uint32_t b) const {
    const Eigen::Vector3d u = (mesh_.vertices[a] - mesh_.vertices[apex]).cast<double>();
    const Eigen::Vector3d v = (mesh_.vertices[b] - mesh_.vertices[apex]).cast<double>();
    return std::atan2(u.cross(v).norm(), u.dot(v));
  }

  core::TriangleMesh& mesh_;
  std::vector<Triangle> faces_;
  const std::function<bool(uint32_t, uint32_t)>& is_edge_;
  absl::flat_hash_map<uint64_t, std::array<uint32_t, 2>> edges_;  // Its faces; kNoFace: a border edge.
  size_t added_ = 0;
};

// Cuts `loop` by shortest chords (each between vertices at least a third of the loop apart)
// into loops of at most kDirectEdges edges; the chords go into `chords`. False where no chord
// is free to take.
bool CutLoop(const std::vector<uint32_t>& loop, const std::vector<Vec3f>& vertices,
             const std::function<bool(uint32_t, uint32_t)>& is_edge, absl::flat_hash_set<uint64_t>& chords,
             std::vector<std::vector<uint32_t>>& pieces) {
  std::vector<std::vector<uint32_t>> pending = {loop};
  while (!pending.empty()) {
    std::vector<uint32_t> piece = std::move(pending.back());
    pending.pop_back();
    const size_t n = piece.size();
    if (n <= kDirectEdges) {
      pieces.push_back(std::move(piece));
      continue;
    }
    absl::flat_hash_map<uint32_t, int> passes;
    for (uint32_t v : piece) ++passes[v];
    double best = std::numeric_limits<double>::infinity();
    size_t best_i = 0, best_j = 0;
    for (size_t i = 0; i < n; ++i) {
      if (passes[piece[i]] > 1) continue;
      for (size_t step = n / 3; step <= n / 2; ++step) {
        const size_t j = (i + step) % n;
        const uint32_t a = piece[i], b = piece[j];
        if (passes[b] > 1) continue;
        const double d2 = static_cast<double>((vertices[a] - vertices[b]).squaredNorm());
        if (d2 >= best || chords.contains(Undirected(a, b)) || is_edge(a, b)) continue;
        best = d2, best_i = i, best_j = j;
      }
    }
    if (best == std::numeric_limits<double>::infinity()) return false;
    chords.insert(Undirected(piece[best_i], piece[best_j]));
    std::vector<uint32_t> one, other;
    for (size_t k = best_i;; k = (k + 1) % n) {
      one.push_back(piece[k]);
      if (k == best_j) break;
    }
    for (size_t k = best_j;; k = (k + 1) % n) {
      other.push_back(piece[k]);
      if (k == best_i) break;
    }
    pending.push_back(std::move(one));
    pending.push_back(std::move(other));
  }
  return true;
}

// How the Laplacian weighs a vertex's neighbours.
enum class Weights {
  // Alike: its zero puts each vertex at its neighbours' centroid, which evens out the
  // triangles' shapes (not the surface's).
  kUniform,
  // The discrete mean curvature normal: half the cotangents of the angles opposite an edge,
  // clamped at a small positive value (an obtuse pair would pull the wrong way), over the
  // vertex's share of the faces' area (a third of each). Its zero follows the surface's shape,
  // where umbrella weights follow the triangulation and sag to about half a smooth bulge.
  kCotangent,
};

// Each vertex's neighbours with the weights of the edges to them, from `faces` (every face
// around the vertices that matter).
class Laplacian {
 public:
  Laplacian(const std::vector<Vec3f>& vertices, const std::vector<Triangle>& faces, Weights kind) {
    absl::flat_hash_map<uint64_t, double> edge_weight;
    absl::flat_hash_map<uint32_t, double> area;
    for (const Triangle& t : faces) {
      for (size_t s = 0; s < 3; ++s) {
        const uint32_t apex = t[s], a = t[(s + 1) % 3], b = t[(s + 2) % 3];
        const Eigen::Vector3d u = (vertices[a] - vertices[apex]).cast<double>();
        const Eigen::Vector3d v = (vertices[b] - vertices[apex]).cast<double>();
        const double sine = u.cross(v).norm();
        if (kind == Weights::kUniform) {
          edge_weight[Undirected(a, b)] = 1, area[apex] = 1;
          continue;
        }
        edge_weight[Undirected(a, b)] += 0.5 * u.dot(v) / std::max(sine, 1e-30);
        area[apex] += sine / 6;
      }
    }
    for (const auto& [key, weight] : edge_weight) {
      const auto a = static_cast<uint32_t>(key >> 32), b = static_cast<uint32_t>(key);
      const double w = std::max(weight, kLeastWeight);
      ring_[a].emplace_back(b, w / std::max(area[a], 1e-30));
      ring_[b].emplace_back(a, w / std::max(area[b], 1e-30));
    }
    // In neighbour order, not the hash map's (seeded per process): the sums, and so the faired
    // positions, are the same to the bit on every run.
    for (auto& [v, ring] : ring_) std::ranges::sort(ring);
  }
  // v's neighbours with their weights; empty for a vertex of none of the faces.
  const std::vector<std::pair<uint32_t, double>>& Ring(uint32_t v) const {
    static const std::vector<std::pair<uint32_t, double>> kNone;
    const auto it = ring_.find(v);
    return it == ring_.end() ? kNone : it->second;
  }

 private:
  static constexpr double kLeastWeight = 1e-2;
  absl::flat_hash_map<uint32_t, std::vector<std::pair<uint32_t, double>>> ring_;
};

// Places the vertices from `first` on where the (bi-)Laplacian of the positions vanishes, the
// others fixed, with the weights from the current positions. `faces` are the filling's and the
// surface's around its border, so that the Laplacian at a border vertex sees the surface beyond
// it (the filling's tangent then follows the surface's). False where the system is singular
// (the positions then stay).
bool Fair(core::TriangleMesh& mesh, uint32_t first, const std::vector<Triangle>& faces, bool thin_plate, Weights kind) {
  const auto unknowns = static_cast<int>(mesh.vertices.size() - first);
  if (unknowns <= 0) return true;
  {
    const Laplacian laplace(mesh.vertices, faces, kind);
    std::vector<Eigen::Triplet<double>> entries;
    Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(unknowns, 3);
    auto add = [&](int row, uint32_t column, double weight) {
      if (column >= first) {
        entries.emplace_back(row, static_cast<int>(column - first), weight);
      } else {
        rhs.row(row) -= weight * mesh.vertices[column].cast<double>().transpose();
      }
    };
    // The Laplacian at w, scaled by `scale`, into `row`.
    auto laplacian = [&](int row, uint32_t w, double scale) {
      double total = 0;
      for (const auto& [n, weight] : laplace.Ring(w)) {
        add(row, n, scale * weight);
        total += weight;
      }
      add(row, w, -scale * total);
    };
    for (int row = 0; row < unknowns; ++row) {
      const uint32_t u = first + static_cast<uint32_t>(row);
      if (!thin_plate) {
        laplacian(row, u, 1.0);
        continue;
      }
      // Scaled by u's area, so that rows weigh alike.
      double total = 0;
      for (const auto& [n, weight] : laplace.Ring(u)) total += weight;
      for (const auto& [n, weight] : laplace.Ring(u)) laplacian(row, n, weight / total);
      laplacian(row, u, -1.0);
    }
    Eigen::SparseMatrix<double> system(unknowns, unknowns);
    system.setFromTriplets(entries.begin(), entries.end());
    Eigen::SparseLU<Eigen::SparseMatrix<double>> solver;
    solver.compute(system);
    if (solver.info() != Eigen::Success) return false;
    const Eigen::MatrixXd positions = solver.solve(rhs);
    if (solver.info() != Eigen::Success || !positions.allFinite()) return false;
    // A nearly singular system (cotangents of a folded patch) solves to positions far off; a
    // fairing stays within about the span of the faces it smooths.
    Eigen::AlignedBox3d span;
    for (const Triangle& t : faces) {
      for (uint32_t v : t) span.extend(mesh.vertices[v].cast<double>());
    }
    const double margin = span.diagonal().norm();
    const Eigen::AlignedBox3d allowed(span.min().array() - margin, span.max().array() + margin);
    for (int row = 0; row < unknowns; ++row) {
      if (!allowed.contains(positions.row(row).transpose())) return false;
    }
    for (int row = 0; row < unknowns; ++row) mesh.vertices[first + row] = positions.row(row).transpose().cast<float>();
  }
  return true;
}

// The median length of the edges of `faces`: the border's own edges can be far shorter (where
// a surface method clipped its triangles).
double MedianEdge(const absl::btree_set<uint32_t>& faces, const core::TriangleMesh& mesh) {
  std::vector<float> lengths;
  for (uint32_t f : faces) {
    const Triangle& t = mesh.faces[f];
    for (size_t s = 0; s < 3; ++s) lengths.push_back((mesh.vertices[t[s]] - mesh.vertices[t[(s + 1) % 3]]).norm());
  }
  if (lengths.empty()) return 0;
  const auto middle = lengths.begin() + static_cast<std::ptrdiff_t>(lengths.size() / 2);
  std::ranges::nth_element(lengths, middle);
  return *middle;
}

// The new vertices' normals (from their faces) and attributes (the border's mean).
void ExtendVertexData(core::TriangleMesh& mesh, size_t first, const std::vector<uint32_t>& border,
                      const std::vector<Triangle>& faces) {
  const size_t count = mesh.vertices.size();
  if (!mesh.normals.empty()) {
    mesh.normals.resize(count, Vec3f::Zero());
    for (const Triangle& t : faces) {
      const Vec3f n = (mesh.vertices[t[1]] - mesh.vertices[t[0]]).cross(mesh.vertices[t[2]] - mesh.vertices[t[0]]);
      for (uint32_t v : t) {
        if (v >= first) mesh.normals[v] += n;
      }
    }
    for (size_t v = first; v < count; ++v) mesh.normals[v].normalize();
  }
  for (core::ScalarAttribute& attribute : mesh.vertex_attributes) {
    double mean = 0;
    for (uint32_t v : border) mean += attribute.values[v];
    attribute.values.resize(count, static_cast<float>(mean / static_cast<double>(border.size())));
  }
}

}  // namespace

absl::StatusOr<HoleFillingStats> FillHoles(core::TriangleMesh& mesh, const HoleFillingParams& params,
                                           core::JobContext& ctx) {
  HoleFillingStats stats;
  if (mesh.faces.empty()) return stats;
  internal::HoleBorders borders(mesh);
  const std::vector<std::vector<uint32_t>> loops = borders.Loops(0);
  stats.holes_left = borders.tangled_loops();
  absl::flat_hash_set<uint64_t> added;  // Edges of the fillings so far.
  const std::function<bool(uint32_t, uint32_t)> is_edge = [&](uint32_t a, uint32_t b) {
    return added.contains(Undirected(a, b)) || borders.IsEdge(a, b);
  };
  const size_t original_vertices = mesh.vertices.size();
  std::vector<uint32_t> around;
  for (size_t hole = 0; hole < loops.size(); ++hole) {
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
    ctx.ReportProgress("filling holes", static_cast<double>(hole) / static_cast<double>(loops.size()));
    const std::vector<uint32_t>& loop = loops[hole];
    if (params.max_border_edges > 0 && static_cast<int64_t>(loop.size()) > params.max_border_edges) {
      ++stats.holes_left;
      continue;
    }
    absl::flat_hash_set<uint64_t> chords;
    std::vector<std::vector<uint32_t>> pieces;
    const std::function<bool(uint32_t, uint32_t)> is_edge_here = [&](uint32_t a, uint32_t b) {
      return chords.contains(Undirected(a, b)) || is_edge(a, b);
    };
    std::vector<Triangle> faces;
    bool triangulated = CutLoop(loop, mesh.vertices, is_edge, chords, pieces);
    for (size_t p = 0; triangulated && p < pieces.size(); ++p) {
      const size_t before = faces.size();
      triangulated = internal::TriangulateLoop(pieces[p], mesh.vertices, is_edge_here, FillingCost, faces);
      // A vertex the pieces share (a pinch) must not take one chord twice.
      for (size_t f = before; f < faces.size(); ++f) {
        for (size_t s = 0; s < 3; ++s) chords.insert(Undirected(faces[f][s], faces[f][(s + 1) % 3]));
      }
    }
    if (!triangulated) {
      ++stats.holes_left;
      continue;
    }
    const auto first = static_cast<uint32_t>(mesh.vertices.size());
    absl::btree_set<uint32_t> surface_faces;
    for (uint32_t v : loop) {
      borders.FacesAround(v, around);
      surface_faces.insert(around.begin(), around.end());
    }
    Patch patch(mesh, std::move(faces), is_edge);
    const double limit = params.edge_scale * MedianEdge(surface_faces, mesh);
    // Four times the vertices that triangles of edge `limit` need over the first triangulation's
    // area (the faired patch bulges, its area grows), and never more than the surface has.
    double area = 0;
    for (const Triangle& t : patch.faces()) {
      area += internal::TriangleArea(mesh.vertices[t[0]], mesh.vertices[t[1]], mesh.vertices[t[2]]);
    }
    const double per_vertex = limit > 0 ? std::numbers::sqrt3 / 2 * limit * limit : 0;
    const size_t wanted = per_vertex > 0 ? static_cast<size_t>(4 * area / per_vertex) : 0;
    const size_t budget = std::min(original_vertices, wanted + loop.size());
    for (int round = 0; round < kRefinements; ++round) {
      const size_t added_so_far = mesh.vertices.size() - first;
      if (added_so_far >= budget) break;
      const size_t split = patch.Refine(limit, budget - added_so_far);
      if (split == 0) break;
      patch.Flip();
    }
    // Relaxed before it is faired: each new vertex at its neighbours' centroid, flipped again,
    // so that the cotangents the fairing weighs with come from well-shaped triangles. (Splitting
    // the edges the relaxation stretches, between rounds, grows the patch without end.)
    bool faired = true;
    for (int relax = 0; relax < kRelaxations && faired; ++relax) {
      faired = Fair(mesh, first, patch.faces(), /*thin_plate=*/false, Weights::kUniform);
      patch.Flip();
    }
    std::vector<Triangle> fairing_faces = patch.faces();
    for (uint32_t f : surface_faces) fairing_faces.push_back(mesh.faces[f]);
    // One solve: weights taken again from the faired positions drift the vertices along the
    // surface and diverge within a few rounds.
    // Umbrella weights where the cotangents fail: they sag, but their system is never singular.
    if (faired && !Fair(mesh, first, fairing_faces, params.thin_plate, Weights::kCotangent)) {
      faired = Fair(mesh, first, fairing_faces, params.thin_plate, Weights::kUniform);
      stats.umbrella_faired += faired ? 1 : 0;
    }
    if (!faired) ++stats.unfaired;
    ExtendVertexData(mesh, first, loop, patch.faces());
    for (const Triangle& t : patch.faces()) {
      for (size_t s = 0; s < 3; ++s) added.insert(Undirected(t[s], t[(s + 1) % 3]));
      mesh.faces.push_back(t);
    }
    ++stats.holes_filled;
    stats.faces_added += static_cast<int64_t>(patch.faces().size());
  }
  stats.vertices_added = static_cast<int64_t>(mesh.vertices.size() - original_vertices);
  return stats;
}

}  // namespace lsqsurf::extract
