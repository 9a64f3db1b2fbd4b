#include "worker/extract/creases.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <Eigen/LU>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numbers>
#include <optional>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/extract/marching_tets.h"

namespace lsqsurf::extract::internal {
namespace {

using core::Vec3d;
using core::Vec3f;

// A crease point must lie within kMaxResidualShare of its edge's length of F = 0: a fitted
// function's crease is a blend of neighbouring fits' creases, slightly rounded, and the tangent
// planes' intersection is the better estimate of the sharp one (fandisk 100k: 0.02 left 0.13 % of
// the true surface farther than 1e-3 of the diagonal, 0.1 leaves 0.077 %). A corner point is held
// to kMaxCornerResidualShare of the triangle. Both must project onto the middle of the edge (away
// from the ends by kEndMargin) and lie within kMaxOffsetShare of its length of it.
constexpr double kMaxResidualShare = 0.1;
constexpr double kMaxCornerResidualShare = 0.02;
constexpr double kEndMargin = 0.02;
constexpr double kMaxOffsetShare = 0.5;
// Acute edges: the geometric largest offset (½ tan(θ/2) of the edge) with this slack, capped.
constexpr double kOffsetSlack = 1.2;
constexpr double kMaxOffsetCap = 4.0;

// An end of an edge that lies this close to the crease (share of the edge) is moved onto it.
// Across an acute crease (normals more than 90° apart) the chords cut the tip off deeper, and the
// crease often lies beyond the nearer end (the triangle of the ends and the crease point is obtuse
// there), so no split can reach it: such an end moves up to a whole edge, unless a triangle turns
// (a pentagonal pyramid's 50° base edges at 200k points: share of the surface farther than 1e-3
// of the diagonal 1.06e-3 -> 2.4e-4).
constexpr double kMaxSnapShare = 0.15;
constexpr double kMaxAcuteSnapShare = 1.0;
// Where that end cannot move, the edge is split instead unless the crease point is closer than
// this share of the edge to an end (a vertex there would merge with the end in any delivery).
constexpr double kStuckMargin = 1e-3;

// A least-squares corner: the tangent planes of a vertex's two rings must span three directions
// (the smallest eigenvalue of Σ n nᵀ at least kCornerSpread of the largest; a smooth patch's
// normals do not), the corner must lie within kCornerReach of its longest edge from the vertex,
// and corners closer than kSameCornerShare of that edge are one.
constexpr double kCornerSpread = 0.02;
constexpr double kCornerReach = 1.5;
constexpr double kSameCornerShare = 0.25;
// A vertex that must move farther than its edges to reach the corner (an acute tip that the
// lattice cut off) may find F off by this share of the move: the fits round a corner at their
// own scale, not the mesh's (a pentagonal pyramid's base corner at 100k points: F = 7e-5 there
// against 5e-5 allowed by its 2.6e-3 edges, so the tip stayed cut by 2e-3 of the diagonal). The
// planes of a corner rounded with radius r meet 0.73 r off F, a move of r or less away.
constexpr double kMaxCornerMoveResidualShare = 0.05;

struct CreaseHit {
  Vec3d point = Vec3d::Constant(std::numeric_limits<double>::quiet_NaN());  // The split point, or NaN.
  int snap_end = -1;                                                        // 0 (a) or 1 (b): move it...
  Vec3d snap_to = Vec3d::Zero();                                            // ...onto this crease point.
  // Where the edge is split instead when the end cannot move (a triangle would turn), or NaN: a
  // sliver keeps the crease where the curve would otherwise cut across a face.
  Vec3d split_if_stuck = Vec3d::Constant(std::numeric_limits<double>::quiet_NaN());
};

// Points found again within `tolerance` of where they were put (a hash grid of that cell size).
// New vertices closer than a delivery's quantization step to another one would merge in it.
class NearbyPoints {
 public:
  explicit NearbyPoints(double tolerance) : tolerance_(tolerance) {}
  bool Near(const Vec3f& p) const {
    const std::array<int64_t, 3> key = Key(p);
    for (int64_t dx = -1; dx <= 1; ++dx) {
      for (int64_t dy = -1; dy <= 1; ++dy) {
        for (int64_t dz = -1; dz <= 1; ++dz) {
          const auto it = cells_.find({key[0] + dx, key[1] + dy, key[2] + dz});
          if (it == cells_.end()) continue;
          for (const Vec3f& q : it->second) {
            if ((q - p).cast<double>().norm() <= tolerance_) return true;
          }
        }
      }
    }
    return false;
  }
  void Insert(const Vec3f& p) { cells_[Key(p)].push_back(p); }

 private:
  std::array<int64_t, 3> Key(const Vec3f& p) const {
    return {static_cast<int64_t>(std::floor(p.x() / tolerance_)), static_cast<int64_t>(std::floor(p.y() / tolerance_)),
            static_cast<int64_t>(std::floor(p.z() / tolerance_))};
  }
  double tolerance_;
  absl::flat_hash_map<std::array<int64_t, 3>, std::vector<Vec3f>> cells_;
};

// 16 steps of a 30-bit quantization of the mesh's box (the finest a delivery uses).
double MergeTolerance(const core::TriangleMesh& mesh) {
  Eigen::AlignedBox3f box;
  for (const Vec3f& p : mesh.vertices) box.extend(p);
  return box.isEmpty() ? 0.0 : std::ldexp(static_cast<double>(box.sizes().maxCoeff()), -26);
}

bool OnSurface(const core::ImplicitFunction& field, const Vec3d& x, double tolerance) {
  const core::FieldValue f = field.Value(x);
  return f.defined && std::abs(f.value) <= tolerance;
}

// The point of the line where the planes (a, na) and (b, nb) meet that is nearest the midpoint
// of a–b, when it is a crease point of F inside the edge. Where the line passes next to an end
// instead, that end's nearest point on the line, so that the end can be moved onto the crease
// (a split there would make a sliver, and without either the crease would miss by up to the
// margin).
CreaseHit CreasePoint(const core::ImplicitFunction& field, const Vec3d& a, const Vec3d& na, const Vec3d& b,
                      const Vec3d& nb) {
  const CreaseHit none;
  const Vec3d m = 0.5 * (a + b);
  // x = m + s na + t nb with na·(x − a) = 0 and nb·(x − b) = 0.
  const double c = na.dot(nb);
  const double det = 1 - c * c;
  if (!(det > 1e-6)) return none;
  const double ra = na.dot(a - m), rb = nb.dot(b - m);
  const double s = (ra - c * rb) / det, t = (rb - c * ra) / det;
  const Vec3d x = m + s * na + t * nb;
  const Vec3d edge = b - a;
  const double length = edge.norm();
  // Across an acute edge the crease lies farther from the chord than half its length: up to
  // ½ tan(θ/2) of it, θ the angle between the normals (0.5 at a right angle, 1.07 where a
  // pyramid's side meets its base at 50°, which a fixed half missed along the whole edge).
  const double max_offset =
      length * std::min(kMaxOffsetCap, std::max(kMaxOffsetShare, kOffsetSlack * 0.5 * std::sqrt((1 - c) / (1 + c))));
  const double along = (x - a).dot(edge) / (length * length);
  if (!(along > kEndMargin && along < 1 - kEndMargin)) {
    const bool acute = c < 0;
    if (!(along > -kEndMargin && along < 1 + kEndMargin) && !acute) return none;
    const int end = along <= 0.5 ? 0 : 1;
    const Vec3d e = end == 0 ? a : b;
    const Vec3d direction = na.cross(nb).normalized();
    const Vec3d p = x + direction * (e - x).dot(direction);
    if (!((p - e).norm() <= (acute ? kMaxAcuteSnapShare : kMaxSnapShare) * length) ||
        !OnSurface(field, p, kMaxResidualShare * length))
      return none;
    CreaseHit hit;
    hit.snap_end = end, hit.snap_to = p;
    if (along > kStuckMargin && along < 1 - kStuckMargin && (x - (a + along * edge)).norm() <= max_offset &&
        OnSurface(field, x, kMaxResidualShare * length)) {
      hit.split_if_stuck = x;
    }
    return hit;
  }
  if ((x - (a + along * edge)).norm() > max_offset) return none;
  if (!OnSurface(field, x, kMaxResidualShare * length)) return none;
  CreaseHit hit;
  hit.point = x;
  return hit;
}

// Where the tangent planes of a triangle's three corners meet, if that is a corner of F near
// the triangle; else the mean of `fallback`.
Vec3d CornerPoint(const core::ImplicitFunction& field, const std::array<Vec3d, 3>& p, const std::array<Vec3d, 3>& n,
                  const std::array<Vec3d, 3>& fallback) {
  const Vec3d mean = (fallback[0] + fallback[1] + fallback[2]) / 3;
  Eigen::Matrix3d m;
  m << n[0].transpose(), n[1].transpose(), n[2].transpose();
  const Vec3d rhs(n[0].dot(p[0]), n[1].dot(p[1]), n[2].dot(p[2]));
  const Eigen::FullPivLU<Eigen::Matrix3d> lu(m);
  if (lu.rank() < 3 || std::abs(lu.determinant()) < 0.05) return mean;
  const Vec3d x = lu.solve(rhs);
  double size = 0;
  for (int i = 0; i < 3; ++i)
    size = std::max(size, (p[static_cast<size_t>(i)] - p[static_cast<size_t>((i + 1) % 3)]).norm());
  if (!x.allFinite() || (x - mean).norm() > size) return mean;
  const core::FieldValue f = field.Value(x);
  return f.defined && std::abs(f.value) <= kMaxCornerResidualShare * size ? x : mean;
}

// Moves each edge end that a crease passes next to onto its nearest crease point (the closest
// of its edges' hits), unless that turns one of its triangles over. Returns the ends that stayed.
absl::flat_hash_set<uint32_t> SnapEndsOntoCreases(std::span<const uint64_t> candidates, std::span<const CreaseHit> hits,
                                                  core::TriangleMesh& mesh, CreaseCounts& counts) {
  absl::flat_hash_map<uint32_t, Vec3d> target;
  for (size_t k = 0; k < candidates.size(); ++k) {
    if (hits[k].snap_end < 0) continue;
    const auto v = static_cast<uint32_t>(hits[k].snap_end == 0 ? candidates[k] >> 32 : candidates[k] & 0xffffffffu);
    const Vec3d from = mesh.vertices[v].cast<double>();
    auto [it, fresh] = target.emplace(v, hits[k].snap_to);
    if (!fresh && (hits[k].snap_to - from).squaredNorm() < (it->second - from).squaredNorm())
      it->second = hits[k].snap_to;
  }
  if (target.empty()) return {};
  absl::flat_hash_map<uint32_t, Vec3f> old_position;
  for (const auto& [v, p] : target) {
    old_position[v] = mesh.vertices[v];
    mesh.vertices[v] = p.cast<float>();
  }
  // A move that turns a triangle (its normal more than 90° from before) is undone; undoing one
  // can turn a triangle checked before, hence a few passes.
  for (bool undone = true; undone;) {
    undone = false;
    for (const core::Triangle& t : mesh.faces) {
      bool moved = false;
      for (uint32_t v : t) moved = moved || old_position.contains(v);
      if (!moved) continue;
      auto old_at = [&](uint32_t v) {
        auto it = old_position.find(v);
        return (it == old_position.end() ? mesh.vertices[v] : it->second).cast<double>();
      };
      auto now_at = [&](uint32_t v) { return mesh.vertices[v].cast<double>(); };
      const Vec3d n_old = (old_at(t[1]) - old_at(t[0])).cross(old_at(t[2]) - old_at(t[0]));
      const Vec3d n_new = (now_at(t[1]) - now_at(t[0])).cross(now_at(t[2]) - now_at(t[0]));
      if (n_old.dot(n_new) > 0) continue;
      for (uint32_t v : t) {
        if (auto it = old_position.find(v); it != old_position.end() && mesh.vertices[v] != it->second) {
          mesh.vertices[v] = it->second;
          undone = true;
        }
      }
    }
  }
  absl::flat_hash_set<uint32_t> stuck;
  for (const auto& [v, p] : old_position) {
    if (mesh.vertices[v] != p) {
      ++counts.snapped_vertices;
    } else {
      stuck.insert(v);
    }
  }
  return stuck;
}

// The faces of `mesh` with their split edges (`split`: edge → crease vertex) cut along the
// creases; a triangle with three splits gets a corner vertex, shared with the triangles that find
// the same position (`vertex_at`: new vertices by position).
// `cells` (when given) holds a value per face, which its pieces inherit.
std::vector<core::Triangle> SplitFaces(const core::ImplicitFunction& field,
                                       const absl::flat_hash_map<uint64_t, uint32_t>& split,
                                       absl::flat_hash_map<std::array<float, 3>, uint32_t>& vertex_at,
                                       core::TriangleMesh& mesh, CreaseCounts& counts, std::vector<uint64_t>* cells) {
  std::vector<core::Triangle> faces;
  faces.reserve(mesh.faces.size() + 2 * static_cast<size_t>(counts.crease_vertices));
  std::vector<uint64_t> piece_cells;
  auto v3 = [&](uint32_t v) { return Vec3d(mesh.vertices[v].cast<double>()); };
  for (size_t source = 0; source < mesh.faces.size(); ++source) {
    const core::Triangle& t = mesh.faces[source];
    std::array<uint32_t, 3> s;  // s[i]: the crease vertex on edge t[i]–t[i+1].
    int count = 0;
    for (size_t i = 0; i < 3; ++i) {
      const auto it = split.find(EdgeKey(t[i], t[(i + 1) % 3]));
      s[i] = it == split.end() ? UINT32_MAX : it->second;
      count += s[i] != UINT32_MAX;
    }
    if (count == 0) {
      faces.push_back(t);
    } else if (count == 1) {
      const size_t i = s[0] != UINT32_MAX ? 0 : s[1] != UINT32_MAX ? 1 : 2;
      const uint32_t u = t[i], v = t[(i + 1) % 3], w = t[(i + 2) % 3];
      faces.push_back({u, s[i], w});
      faces.push_back({s[i], v, w});
    } else if (count == 2) {
      // Rotate so that the unsplit edge is t[2]–t[0]: the crease runs s[0]–s[1], around t[1].
      const size_t j = s[0] == UINT32_MAX ? 1 : s[1] == UINT32_MAX ? 2 : 0;
      const uint32_t v0 = t[j], v1 = t[(j + 1) % 3], v2 = t[(j + 2) % 3];
      const uint32_t s0 = s[j], s1 = s[(j + 1) % 3];
      faces.push_back({s0, v1, s1});
      if ((v3(v0) - v3(s1)).squaredNorm() <= (v3(s0) - v3(v2)).squaredNorm()) {
        faces.push_back({v0, s0, s1});
        faces.push_back({v0, s1, v2});
      } else {
        faces.push_back({v0, s0, v2});
        faces.push_back({s0, s1, v2});
      }
    } else {
      const std::array<Vec3d, 3> p = {v3(t[0]), v3(t[1]), v3(t[2])};
      const std::array<Vec3d, 3> n = {mesh.normals[t[0]].cast<double>(), mesh.normals[t[1]].cast<double>(),
                                      mesh.normals[t[2]].cast<double>()};
      const Vec3f corner = CornerPoint(field, p, n, {v3(s[0]), v3(s[1]), v3(s[2])}).cast<float>();
      // Neighbouring triangles around one true corner (of an exact solid) find the same point:
      // they share one vertex there, and the faces that fold onto each other go below.
      auto [at, fresh] = vertex_at.emplace(std::array<float, 3>{corner.x(), corner.y(), corner.z()},
                                           static_cast<uint32_t>(mesh.vertices.size()));
      const uint32_t q = at->second;
      if (fresh) {
        mesh.vertices.push_back(corner);
        const Vec3f nq = mesh.normals[t[0]] + mesh.normals[t[1]] + mesh.normals[t[2]];
        mesh.normals.push_back(nq.norm() > 0 ? Vec3f(nq.normalized()) : mesh.normals[t[0]]);
        ++counts.corners;
      }
      for (size_t i = 0; i < 3; ++i) {
        faces.push_back({t[i], s[i], q});
        faces.push_back({s[i], t[(i + 1) % 3], q});
      }
    }
    if (cells != nullptr) piece_cells.resize(faces.size(), (*cells)[source]);
  }
  std::vector<char> drop(faces.size(), 0);
  // Triangles between two edges that share their crease vertex have collapsed.
  for (size_t f = 0; f < faces.size(); ++f) {
    const core::Triangle& t = faces[f];
    drop[f] = t[0] == t[1] || t[1] == t[2] || t[2] == t[0];
  }
  // Two triangles on the same three vertices (from fans around one shared new vertex) enclose
  // nothing: both go, which keeps every edge with two faces.
  if (!vertex_at.empty()) {
    absl::flat_hash_map<std::array<uint32_t, 3>, uint32_t> seen;
    for (uint32_t f = 0; f < faces.size(); ++f) {
      if (drop[f]) continue;
      std::array<uint32_t, 3> key = faces[f];
      std::sort(key.begin(), key.end());
      auto [it, fresh] = seen.emplace(key, f);
      if (fresh) continue;
      if (it->second != UINT32_MAX) {
        drop[it->second] = drop[f] = 1;
        it->second = UINT32_MAX;
      } else {
        it->second = f;
      }
    }
  }
  size_t kept = 0;
  for (size_t f = 0; f < faces.size(); ++f) {
    if (drop[f]) continue;
    if (cells != nullptr) piece_cells[kept] = piece_cells[f];
    faces[kept++] = faces[f];
  }
  faces.resize(kept);
  if (cells != nullptr) {
    piece_cells.resize(kept);
    *cells = std::move(piece_cells);
  }
  return faces;
}

// A face left between three sheets: each of its edges borders a face of another sheet, so it cuts
// off the corner where the sheets meet (where a crease ends on another, as a box's edge where a
// sphere cuts it, no face had three splits). The corner, where the three neighbours' planes
// meet, becomes a vertex and the face a fan of three around it, each piece in the plane of the
// neighbour across its edge. Faces touching a vertex from
// `first_new` on (the crease vertices) are looked at.
void InsertCutCorners(const core::ImplicitFunction& field, double cos_crease, uint32_t first_new,
                      core::TriangleMesh& mesh, CreaseCounts& counts, std::vector<uint64_t>* cells) {
  // The faces of each new vertex.
  std::vector<uint32_t> start, incident;
  core::IncidentFaces(mesh, start, incident, first_new);
  auto v3 = [&](uint32_t v) { return Vec3d(mesh.vertices[v].cast<double>()); };
  auto unit_normal = [&](const core::Triangle& t) {
    const Vec3d n = (v3(t[1]) - v3(t[0])).cross(v3(t[2]) - v3(t[0]));
    return n.norm() > 0 ? Vec3d(n.normalized()) : Vec3d::Zero();
  };
  // The one other face on edge a–b (a new vertex), or UINT32_MAX.
  auto across = [&](uint32_t f, uint32_t a, uint32_t b) {
    uint32_t found = UINT32_MAX;
    for (uint32_t k = start[a - first_new]; k < start[a - first_new + 1]; ++k) {
      const uint32_t g = incident[k];
      const core::Triangle& t = mesh.faces[g];
      if (g == f || (t[0] != b && t[1] != b && t[2] != b)) continue;
      if (found != UINT32_MAX) return UINT32_MAX;  // Non-manifold: left alone.
      found = g;
    }
    return found;
  };
  // Such a face lies between crease lines, so two of its corners at least are crease points:
  // each of its edges then has a new end to look the neighbour up by.
  std::vector<std::pair<uint32_t, Vec3f>> found;  // Face → the corner it cuts off.
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    const core::Triangle t = mesh.faces[f];
    if ((t[0] >= first_new) + (t[1] >= first_new) + (t[2] >= first_new) < 2) continue;
    const Vec3d nf = unit_normal(t);
    std::array<Vec3d, 3> n;
    bool cut = nf.squaredNorm() > 0;
    for (size_t i = 0; i < 3 && cut; ++i) {
      const uint32_t a = t[i], b = t[(i + 1) % 3];
      const uint32_t g = a >= first_new ? across(f, a, b) : across(f, b, a);
      cut = g != UINT32_MAX;
      if (cut) n[i] = unit_normal(mesh.faces[g]);
    }
    for (size_t i = 0; i < 3 && cut; ++i) cut = n[i].dot(n[(i + 1) % 3]) < cos_crease;
    if (!cut) continue;
    Eigen::Matrix3d m;
    m << n[0].transpose(), n[1].transpose(), n[2].transpose();
    const Eigen::FullPivLU<Eigen::Matrix3d> lu(m);
    if (lu.rank() < 3 || std::abs(lu.determinant()) < 0.05) continue;
    const Vec3d x = lu.solve(Vec3d(n[0].dot(v3(t[0])), n[1].dot(v3(t[1])), n[2].dot(v3(t[2]))));
    double size = 0;
    for (size_t i = 0; i < 3; ++i) size = std::max(size, (v3(t[i]) - v3(t[(i + 1) % 3])).norm());
    const Vec3d centroid = (v3(t[0]) + v3(t[1]) + v3(t[2])) / 3;
    if (!x.allFinite() || (x - centroid).norm() > size || !OnSurface(field, x, kMaxCornerResidualShare * size))
      continue;
    bool at_a_vertex = false;  // Pieces that would be slivers of no width: the corner is there.
    for (uint32_t v : t) at_a_vertex = at_a_vertex || (x - v3(v)).norm() <= kStuckMargin * size;
    if (at_a_vertex) continue;
    // Each piece must face like the neighbour across its edge (the corner lies over the face).
    bool turns = false;
    for (size_t i = 0; i < 3; ++i) {
      turns = turns || (v3(t[(i + 1) % 3]) - v3(t[i])).cross(x - v3(t[i])).dot(n[i]) <= 0;
    }
    if (!turns) found.emplace_back(f, x.cast<float>());
  }
  if (found.empty()) return;
  // One vertex per corner, and none where a vertex is already (a solid's corner on the lattice):
  // two vertices at one position (or a quantization step apart) would merge in a delivery.
  NearbyPoints taken(MergeTolerance(mesh));
  for (uint32_t f : incident) {
    for (uint32_t v : mesh.faces[f]) taken.Insert(mesh.vertices[v]);
  }
  for (const auto& [f, corner] : found) {
    if (taken.Near(corner)) continue;
    taken.Insert(corner);
    const core::Triangle t = mesh.faces[f];
    const auto q = static_cast<uint32_t>(mesh.vertices.size());
    mesh.vertices.push_back(corner);
    const Vec3d nf = unit_normal(t);
    mesh.normals.push_back(nf.cast<float>());
    ++counts.corners;
    mesh.faces[f] = {t[0], t[1], q};
    mesh.faces.push_back({t[1], t[2], q});
    mesh.faces.push_back({t[2], t[0], q});
    if (cells != nullptr) cells->resize(mesh.faces.size(), (*cells)[f]);
  }
}

// A corner where more than three sheets meet, or one that no triangle held three splits of, is
// cut off by the triangles around it (a convex polytope's corner of five faces stayed a cell's
// size away). Every vertex whose two-ring normals span three directions finds the point nearest
// all of their tangent planes (the least-squares corner of dual contouring); where that is a
// corner of F beside the vertex, the candidate nearest it moves there, unless one of its
// triangles would turn over. Vertices marked in `fixed` stay.
void SnapVerticesOntoCorners(const core::ImplicitFunction& field, double cos_crease, core::TriangleMesh& mesh,
                             CreaseCounts& counts, core::JobContext& ctx, std::span<const char> fixed) {
  const size_t n = mesh.vertices.size();
  // The vertex → vertex adjacency (compressed rows) and the vertices beside a crease.
  std::vector<uint32_t> offsets(n + 1, 0), neighbours;
  std::vector<char> near_crease(n, 0);
  for (const core::Triangle& t : mesh.faces) {
    for (size_t i = 0; i < 3; ++i) offsets[t[i] + 1] += 2;
    for (size_t i = 0; i < 3; ++i) {
      if (mesh.normals[t[i]].dot(mesh.normals[t[(i + 1) % 3]]) < cos_crease)
        near_crease[t[i]] = near_crease[t[(i + 1) % 3]] = 1;
    }
  }
  for (size_t v = 0; v < n; ++v) offsets[v + 1] += offsets[v];
  neighbours.resize(offsets[n]);
  {
    std::vector<uint32_t> fill(offsets.begin(), offsets.end() - 1);
    for (const core::Triangle& t : mesh.faces) {
      for (size_t i = 0; i < 3; ++i) {
        neighbours[fill[t[i]]++] = t[(i + 1) % 3];
        neighbours[fill[t[i]]++] = t[(i + 2) % 3];
      }
    }
  }
  auto ring = [&](uint32_t v) {
    return std::span<const uint32_t>(neighbours.data() + offsets[v], offsets[v + 1] - offsets[v]);
  };
  struct Candidate {
    uint32_t vertex;
    double distance;  // From the vertex to its corner.
    double longest;   // The vertex's longest edge.
    Vec3d corner;
  };
  std::vector<uint32_t> looked_at;
  for (uint32_t v = 0; v < n; ++v) {
    if (near_crease[v] && (fixed.empty() || v >= fixed.size() || !fixed[v])) looked_at.push_back(v);
  }
  std::vector<std::optional<Candidate>> found(looked_at.size());
  (void)core::ParallelFor(
      looked_at.size(), 256,
      [&](size_t begin, size_t end) {
        std::vector<uint32_t> two_ring;
        for (size_t k = begin; k < end; ++k) {
          const uint32_t v = looked_at[k];
          const Vec3d p = mesh.vertices[v].cast<double>();
          double longest = 0;
          two_ring.assign({v});
          for (uint32_t a : ring(v)) {
            longest = std::max(longest, (mesh.vertices[a].cast<double>() - p).norm());
            two_ring.push_back(a);
            for (uint32_t b : ring(a)) two_ring.push_back(b);
          }
          std::sort(two_ring.begin(), two_ring.end());
          two_ring.erase(std::unique(two_ring.begin(), two_ring.end()), two_ring.end());
          Eigen::Matrix3d planes = Eigen::Matrix3d::Zero();
          Vec3d rhs = Vec3d::Zero();
          for (uint32_t a : two_ring) {
            const Vec3d na = mesh.normals[a].cast<double>();
            planes += na * na.transpose();
            rhs += na * na.dot(mesh.vertices[a].cast<double>());
          }
          const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(planes);
          // Three directions: the weakest spans at least kCornerSpread of the strongest.
          if (eigen.info() != Eigen::Success || !(eigen.eigenvalues()(0) > kCornerSpread * eigen.eigenvalues()(2))) {
            continue;
          }
          const Vec3d x = eigen.eigenvectors() * eigen.eigenvalues().cwiseInverse().asDiagonal() *
                          eigen.eigenvectors().transpose() * rhs;
          const double distance = (x - p).norm();
          if (!x.allFinite() || distance > kCornerReach * longest ||
              !OnSurface(field, x, std::max(kMaxCornerResidualShare * longest, kMaxCornerMoveResidualShare * distance)))
            continue;
          found[k] = Candidate{v, distance, longest, x};
        }
      },
      &ctx);
  std::vector<Candidate> candidates;
  for (auto& c : found) {
    if (c) candidates.push_back(*c);
  }
  // The nearest vertex takes each corner; others that found the same one stay.
  std::sort(candidates.begin(), candidates.end(),
            [](const Candidate& a, const Candidate& b) { return a.distance < b.distance; });
  std::vector<Vec3d> taken;  // Few corners: a list.
  for (const Candidate& c : candidates) {
    const double same = kSameCornerShare * c.longest;
    if (std::any_of(taken.begin(), taken.end(), [&](const Vec3d& t) { return (t - c.corner).norm() <= same; }))
      continue;
    // A vertex there already (a corner found by the splits): nothing to move.
    if (c.distance <= same || std::any_of(ring(c.vertex).begin(), ring(c.vertex).end(), [&](uint32_t a) {
          return (mesh.vertices[a].cast<double>() - c.corner).norm() <= same;
        })) {
      taken.push_back(c.corner);
      continue;
    }
    // The normal of the vertex's i-th triangle (its ring holds each triangle's other two corners
    // in order) were the vertex at `at`.
    const auto face_normal = [&](size_t i, const Vec3d& at) {
      const Vec3d a = mesh.vertices[ring(c.vertex)[i]].cast<double>(),
                  b = mesh.vertices[ring(c.vertex)[i + 1]].cast<double>();
      return Vec3d((a - at).cross(b - at));
    };
    const Vec3f before = mesh.vertices[c.vertex];
    bool turned = false;
    for (size_t i = 0; i + 1 < ring(c.vertex).size(); i += 2) {
      turned |= !(face_normal(i, c.corner).dot(face_normal(i, before.cast<double>())) > 0);
    }
    if (turned) continue;  // The next nearest may move.
    mesh.vertices[c.vertex] = c.corner.cast<float>();
    taken.push_back(c.corner);
    ++counts.corners;
  }
}

}  // namespace

absl::Status SharpenCreases(const core::ImplicitFunction& field, double crease_angle, core::TriangleMesh& mesh,
                            CreaseCounts& counts, core::JobContext& ctx, std::span<const char> fixed,
                            std::vector<uint64_t>* face_cells) {
  const double cos_crease = std::cos(crease_angle * std::numbers::pi / 180);
  // The edges whose ends disagree, each once.
  absl::flat_hash_map<uint64_t, uint32_t> split;  // Edge → its crease vertex (UINT32_MAX: none).
  absl::flat_hash_set<uint64_t> near_edges;       // Every edge of a triangle with a candidate.
  std::vector<uint64_t> candidates;
  for (const core::Triangle& t : mesh.faces) {
    bool any = false;
    for (size_t i = 0; i < 3; ++i) {
      const uint32_t a = t[i], b = t[(i + 1) % 3];
      if (mesh.normals[a].dot(mesh.normals[b]) >= cos_crease) continue;
      if (!fixed.empty() && (fixed[a] || fixed[b])) continue;
      any = true;
      if (split.try_emplace(EdgeKey(a, b), UINT32_MAX).second) candidates.push_back(EdgeKey(a, b));
    }
    if (any) {
      for (size_t i = 0; i < 3; ++i) near_edges.insert(EdgeKey(t[i], t[(i + 1) % 3]));
    }
  }
  if (candidates.empty()) return absl::OkStatus();
  const auto first_new = static_cast<uint32_t>(mesh.vertices.size());
  std::vector<Vec3d> points(candidates.size());
  std::vector<CreaseHit> hits(candidates.size());
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      candidates.size(), 256,
      [&](size_t begin, size_t end) {
        for (size_t k = begin; k < end; ++k) {
          const auto a = static_cast<uint32_t>(candidates[k] >> 32), b = static_cast<uint32_t>(candidates[k]);
          hits[k] = CreasePoint(field, mesh.vertices[a].cast<double>(), mesh.normals[a].cast<double>(),
                                mesh.vertices[b].cast<double>(), mesh.normals[b].cast<double>());
          points[k] = hits[k].point;
        }
      },
      &ctx));
  const absl::flat_hash_set<uint32_t> stuck = SnapEndsOntoCreases(candidates, hits, mesh, counts);
  for (size_t k = 0; k < candidates.size(); ++k) {
    if (hits[k].snap_end < 0) continue;
    const auto v = static_cast<uint32_t>(hits[k].snap_end == 0 ? candidates[k] >> 32 : candidates[k] & 0xffffffffu);
    if (stuck.contains(v)) points[k] = hits[k].split_if_stuck;
  }
  // Two edges of one triangle can meet the crease at the same point (a crease along a grid axis
  // seen from the edges a–b and a–c): they share one vertex, and the sliver between them goes.
  absl::flat_hash_map<uint32_t, std::vector<uint32_t>> candidates_at;  // Vertex → its candidates.
  for (uint32_t k = 0; k < candidates.size(); ++k) {
    if (!points[k].allFinite()) continue;
    candidates_at[static_cast<uint32_t>(candidates[k] >> 32)].push_back(k);
    candidates_at[static_cast<uint32_t>(candidates[k])].push_back(k);
  }
  auto other_end = [](uint64_t edge, uint32_t v) {
    return static_cast<uint32_t>(edge >> 32) == v ? static_cast<uint32_t>(edge) : static_cast<uint32_t>(edge >> 32);
  };
  std::vector<uint32_t> twin(candidates.size(), UINT32_MAX);
  for (uint32_t k = 0; k < candidates.size(); ++k) {
    if (!points[k].allFinite()) continue;
    const auto a = static_cast<uint32_t>(candidates[k] >> 32), b = static_cast<uint32_t>(candidates[k]);
    const double tolerance = 1e-5 * (mesh.vertices[a] - mesh.vertices[b]).norm();
    for (const uint32_t v : {a, b}) {
      for (const uint32_t j : candidates_at[v]) {
        if (j >= k || twin[k] != UINT32_MAX) continue;
        if (!near_edges.contains(EdgeKey(other_end(candidates[k], v), other_end(candidates[j], v)))) continue;
        if ((points[k] - points[j]).norm() <= tolerance) twin[k] = twin[j] != UINT32_MAX ? twin[j] : j;
      }
    }
  }
  // New vertices by position. A crease point that lands on (or a quantization step from) another
  // one or an end of a candidate edge (edges placed symmetrically about an exact solid's crease,
  // crossings converged onto a crease on the lattice) leaves its edge unsplit: two vertices there
  // would merge in any weld by position, and one shared vertex can pinch.
  absl::flat_hash_map<std::array<float, 3>, uint32_t> vertex_at;
  NearbyPoints taken(MergeTolerance(mesh));
  for (const uint64_t edge : candidates) {
    taken.Insert(mesh.vertices[edge >> 32]);
    taken.Insert(mesh.vertices[edge & 0xffffffffu]);
  }
  for (size_t k = 0; k < candidates.size(); ++k) {
    if (!points[k].allFinite() || twin[k] != UINT32_MAX) continue;
    const auto a = static_cast<uint32_t>(candidates[k] >> 32), b = static_cast<uint32_t>(candidates[k]);
    const Vec3f point = points[k].cast<float>();
    if (taken.Near(point)) {
      points[k] = Vec3d::Constant(std::numeric_limits<double>::quiet_NaN());
      continue;
    }
    taken.Insert(point);
    vertex_at.emplace(std::array<float, 3>{point.x(), point.y(), point.z()}, mesh.vertices.size());
    split[candidates[k]] = static_cast<uint32_t>(mesh.vertices.size());
    mesh.vertices.push_back(point);
    const Vec3f n = mesh.normals[a] + mesh.normals[b];
    mesh.normals.push_back(n.norm() > 0 ? Vec3f(n.normalized()) : mesh.normals[a]);
    ++counts.crease_vertices;
  }
  for (size_t k = 0; k < candidates.size(); ++k) {
    if (twin[k] != UINT32_MAX && points[twin[k]].allFinite()) split[candidates[k]] = split[candidates[twin[k]]];
  }
  mesh.faces = SplitFaces(field, split, vertex_at, mesh, counts, face_cells);
  InsertCutCorners(field, cos_crease, first_new, mesh, counts, face_cells);
  SnapVerticesOntoCorners(field, cos_crease, mesh, counts, ctx, fixed);
  return absl::OkStatus();
}

}  // namespace lsqsurf::extract::internal
