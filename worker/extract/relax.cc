#include "worker/extract/relax.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <optional>
#include <span>
#include <utility>
#include <vector>

#include "worker/core/mesh_metrics.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/extract/marching_tets.h"

namespace lsqsurf::extract::internal {
namespace {

using core::IncidentFaces;
using core::Vec3d;
using core::Vec3f;

// Share of the way to the neighbours' mean taken per step.
constexpr double kStepShare = 0.5;
// A tangential move that ends farther than this share of the mean edge from F = 0 is not made
// (the surface bends too much there for one Newton step).
constexpr double kMaxOffsetShare = 0.1;
// A move is not made where the normal would turn by more than about 25° (onto another sheet).
constexpr double kSameSheetCos = 0.9;
// The last relaxation step projects a moved vertex onto F = 0 only where it may have drifted
// farther than this share of an edge from the surface.
constexpr double kUnprojectedDrift = 1e-3;
// Only vertices of triangles whose smallest angle is below this move.
constexpr double kGoodAngleDegrees = 25;
// Edge flips: only between faces within this many degrees of one another (so that the surface
// barely changes and creases are never flipped), only where the smaller angle of the pair grows
// by more than kFlipGain radians; at most kFlipPasses sweeps, ending when one flips fewer than
// 1/kFlipDiminish of what the first did.
constexpr double kFlipFlatDegrees = 20;
constexpr double kFlipGain = 1e-3;
constexpr int kFlipPasses = 8;
constexpr int64_t kFlipDiminish = 50;

// The vertices that stay where they are: from `first_fixed` on (crease splits), on an unsplit
// crease, and on a border.
absl::Status MarkFixedVertices(const core::TriangleMesh& mesh, const std::vector<uint32_t>& start,
                               const std::vector<uint32_t>& incident, uint32_t first_fixed, std::vector<char>& fixed,
                               core::JobContext& ctx) {
  const size_t n = mesh.vertices.size();
  fixed.assign(n, 0);
  // Each vertex looks at the other ends of its faces' edges through it, every edge appearing
  // once per face. It stays where such an edge has not exactly two faces (a border), and where a
  // crease was not split (an edge between two marching vertices whose normals differ by more
  // than about 25°): a vertex on the crease line would slide off it.
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        std::vector<uint32_t> ends;
        for (size_t v = begin; v < end; ++v) {
          if (v >= first_fixed) {
            fixed[v] = 1;
            continue;
          }
          ends.clear();
          for (uint32_t k = start[v]; k < start[v + 1]; ++k) {
            for (uint32_t w : mesh.faces[incident[k]]) {
              if (w != v) ends.push_back(w);
            }
          }
          std::sort(ends.begin(), ends.end());
          for (size_t i = 0; i < ends.size() && !fixed[v];) {
            size_t j = i;
            while (j < ends.size() && ends[j] == ends[i]) ++j;
            if (j - i != 2 || (ends[i] < first_fixed && mesh.normals[v].dot(mesh.normals[ends[i]]) < kSameSheetCos)) {
              fixed[v] = 1;
            }
            i = j;
          }
        }
      },
      &ctx));
  return absl::OkStatus();
}

// Whether the angle between u and w is below the one whose cosine is `cos_limit` (> 0), without
// square roots.
template <typename Vec>
bool AngleBelow(const Vec& u, const Vec& w, double cos_limit) {
  const double dot = u.dot(w);
  return dot > 0 && dot * dot > cos_limit * cos_limit * u.squaredNorm() * w.squaredNorm();
}

// For a triangle with an angle under the one whose cosine is `good_cos`: the index i of its
// longest edge t[i]–t[i+1] (opposite its largest angle: the one a flip can shorten); −1 for a
// good triangle. Measured in `Scalar` precision.
template <typename Scalar>
int8_t PoorTriangleLongestEdge(const core::TriangleMesh& mesh, const core::Triangle& t, double good_cos) {
  using Vec = Eigen::Matrix<Scalar, 3, 1>;
  auto at = [&](size_t i) -> Vec { return mesh.vertices[t[i % 3]].template cast<Scalar>(); };
  int8_t longest = 0;
  Scalar longest2 = -1;
  bool poor = false;
  for (size_t k = 0; k < 3; ++k) {
    const Vec u = at(k + 1) - at(k), w = at(k + 2) - at(k);
    poor |= AngleBelow(u, w, good_cos);
    if (u.squaredNorm() > longest2) longest2 = u.squaredNorm(), longest = static_cast<int8_t>(k);
  }
  return poor ? longest : int8_t{-1};
}

// The smallest angle of the triangle (p, q, r), in radians; 0 for a degenerate one.
double SmallestAngle(const Vec3d& p, const Vec3d& q, const Vec3d& r) {
  const std::array<Vec3d, 3> x = {p, q, r};
  double best = std::numbers::pi;
  for (size_t i = 0; i < 3; ++i) {
    const Vec3d u = x[(i + 1) % 3] - x[i], w = x[(i + 2) % 3] - x[i];
    const double nu = u.norm(), nw = w.norm();
    if (!(nu > 0 && nw > 0)) return 0;
    best = std::min(best, std::acos(std::clamp(u.dot(w) / (nu * nw), -1.0, 1.0)));
  }
  return best;
}

// Where a vertex goes in one relaxation step: part of the way to its neighbours' mean within its
// tangent plane. Also gives the neighbours' mean edge length and an upper estimate of the
// surface's curvature there, the largest turn of the normal per length towards a neighbour
// (exact on a sphere).
Vec3d TangentialTarget(const core::TriangleMesh& mesh, const std::vector<uint32_t>& start,
                       const std::vector<uint32_t>& incident, uint32_t v, double& edge, double* curvature) {
  const Vec3d p = mesh.vertices[v].cast<double>(), normal = mesh.normals[v].cast<double>();
  Vec3d mean = Vec3d::Zero();
  edge = 0;
  double bend = 0;
  int count = 0;
  for (uint32_t k = start[v]; k < start[v + 1]; ++k) {
    for (uint32_t w : mesh.faces[incident[k]]) {
      if (w == v) continue;
      const double length = (mesh.vertices[w].cast<double>() - p).norm();
      mean += mesh.vertices[w].cast<double>();
      edge += length;
      if (curvature) bend = std::max(bend, (mesh.normals[w].cast<double>() - normal).norm() / length);
      ++count;
    }
  }
  mean /= count;
  edge /= count;
  if (curvature) *curvature = bend;
  Vec3d delta = kStepShare * (mean - p);
  delta -= normal.dot(delta) * normal;
  return p + delta;
}

// Whether moving v to x turns one of its triangles over.
bool MoveFolds(const core::TriangleMesh& mesh, const std::vector<uint32_t>& start,
               const std::vector<uint32_t>& incident, uint32_t v, const Vec3d& x) {
  for (uint32_t k = start[v]; k < start[v + 1]; ++k) {
    const core::Triangle& t = mesh.faces[incident[k]];
    std::array<Vec3d, 3> q, q_new;
    for (size_t i = 0; i < 3; ++i) {
      q[i] = mesh.vertices[t[i]].cast<double>();
      q_new[i] = t[i] == v ? x : q[i];
    }
    const Vec3d before = (q[1] - q[0]).cross(q[2] - q[0]), after = (q_new[1] - q_new[0]).cross(q_new[2] - q_new[0]);
    if (before.dot(after) <= 0) return true;
  }
  return false;
}

// One Newton step from x back onto F = 0 along ∇F. Refused (nullopt) where x is farther than
// kMaxOffsetShare of an edge from the surface (it bends too much there for one step) or where ∇F
// turns from `normal` by more than about 25° (x crossed a crease onto another sheet).
std::optional<std::pair<Vec3d, Vec3f>> ProjectOntoSurface(const core::ImplicitFunction& field, const Vec3d& x,
                                                          const Vec3d& normal, double edge) {
  const core::FieldGradient g = field.ValueAndGradientOnly(x);
  const double slope2 = g.gradient.squaredNorm();
  if (!g.defined || !(slope2 > 0) || !(std::abs(g.value) <= kMaxOffsetShare * edge)) return std::nullopt;
  if (g.gradient.dot(normal) < kSameSheetCos * std::sqrt(slope2)) return std::nullopt;
  return std::pair{x - (g.value / slope2) * g.gradient, g.gradient.normalized().cast<float>()};
}

// The relaxation's state across its steps and the flips between them.
class Relaxation {
 public:
  Relaxation(const core::ImplicitFunction& field, core::TriangleMesh& mesh)
      : field_(field), mesh_(mesh), marched_(mesh.vertices), moved_(mesh.vertices.size(), 0) {}

  absl::Status Start(uint32_t first_fixed, core::JobContext& ctx) {
    IncidentFaces(mesh_, start_, incident_);
    return MarkFixedVertices(mesh_, start_, incident_, first_fixed, fixed_, ctx);
  }
  // After the faces changed (flips); which vertices stay does not: flips join nearly coplanar
  // faces only, and borders stay borders.
  void FacesChanged() { IncidentFaces(mesh_, start_, incident_); }

  // The vertices of triangles with an angle under kGoodAngleDegrees move part of the way to
  // their neighbours' mean in their tangent planes. The `last` step also projects the vertices
  // that moved back onto F = 0: the drift of the tangential steps is of second order in the
  // move, so one evaluation per moved vertex replaces one per move, and none is needed where the
  // drift stays below kUnprojectedDrift (bunny 100k: 790k evaluations → 240k).
  absl::Status Step(bool last, core::JobContext& ctx);

  int64_t moved() const { return std::count(moved_.begin(), moved_.end(), 1); }

 private:
  std::optional<std::pair<Vec3d, Vec3f>> Projected(uint32_t v, const Vec3d& x, double edge) const {
    auto projected = ProjectOntoSurface(field_, x, mesh_.normals[v].cast<double>(), edge);
    if (projected && MoveFolds(mesh_, start_, incident_, v, projected->first)) return std::nullopt;
    return projected;
  }

  const core::ImplicitFunction& field_;
  core::TriangleMesh& mesh_;
  const std::vector<Vec3f> marched_;  // Where marching put the vertices, on F = 0.
  std::vector<char> moved_;
  std::vector<uint32_t> start_, incident_;
  std::vector<char> fixed_;
  std::vector<char> poor_;
  std::vector<Vec3f> next_, next_normals_;
};

absl::Status Relaxation::Step(bool last, core::JobContext& ctx) {
  const size_t n = mesh_.vertices.size();
  const double good_cos = std::cos(kGoodAngleDegrees * std::numbers::pi / 180);
  poor_.resize(mesh_.faces.size());
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      mesh_.faces.size(), 4096,
      [&](size_t begin, size_t end) {
        for (size_t f = begin; f < end; ++f) {
          poor_[f] = PoorTriangleLongestEdge<float>(mesh_, mesh_.faces[f], good_cos) >= 0;
        }
      },
      &ctx));
  next_ = mesh_.vertices;
  next_normals_ = mesh_.normals;
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 512,
      [&](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) {
          const auto v = static_cast<uint32_t>(i);
          if (fixed_[v] || start_[v] == start_[v + 1]) continue;
          bool needs = false;
          for (uint32_t k = start_[v]; k < start_[v + 1] && !needs; ++k) needs = poor_[incident_[k]] != 0;
          if (!needs && !(last && moved_[v])) continue;
          double edge = 0, curvature = 0;
          const Vec3d target = TangentialTarget(mesh_, start_, incident_, v, edge, last ? &curvature : nullptr);
          if (!last) {
            if (MoveFolds(mesh_, start_, incident_, v, target)) continue;
            next_[v] = target.cast<float>();
            moved_[v] = 1;
            continue;
          }
          // The moves stay in the tangent plane at the marched vertex, so the surface is about
          // κ·d²/2 away from a vertex moved by d. Where that is below what root refinement leaves
          // anyway, the projection is not worth its evaluation (flat parts, fine meshes).
          const Vec3d here = mesh_.vertices[v].cast<double>();
          const Vec3d x = needs ? target : here;
          const double moved_by = (x - marched_[v].cast<double>()).norm();
          if (0.5 * curvature * moved_by * moved_by <= kUnprojectedDrift * edge &&
              !MoveFolds(mesh_, start_, incident_, v, x)) {
            next_[v] = x.cast<float>();
            moved_[v] = 1;
            continue;
          }
          auto projected = Projected(v, x, edge);
          // Where the target folds or left the sheet, project where the earlier steps put it.
          if (!projected && needs && moved_[v]) projected = Projected(v, here, edge);
          if (projected) {
            next_[v] = projected->first.cast<float>();
            next_normals_[v] = projected->second;
            moved_[v] = 1;
          } else if (moved_[v]) {
            next_[v] = marched_[v];  // Back where marching put it, on the surface.
            moved_[v] = 0;
          }
        }
      },
      &ctx));
  std::swap(mesh_.vertices, next_);
  std::swap(mesh_.normals, next_normals_);
  return absl::OkStatus();
}

}  // namespace

absl::Status EnhanceTriangles(const core::ImplicitFunction& field, int steps, uint32_t first_fixed,
                              core::TriangleMesh& mesh, std::vector<uint64_t>* face_cells, EnhanceCounts& counts,
                              core::JobContext& ctx) {
  counts = {};
  if (steps <= 0) return absl::OkStatus();
  Relaxation relaxation(field, mesh);
  LSQSURF_RETURN_IF_ERROR(relaxation.Start(first_fixed, ctx));
  for (int step = 0; step < steps; ++step) LSQSURF_RETURN_IF_ERROR(relaxation.Step(false, ctx));
  // Flips where the relaxation left thin triangles, then half as many steps again around them
  // (fandisk 100k: smallest-angle p1 15.7°; 13.7° before the flips existed).
  LSQSURF_RETURN_IF_ERROR(FlipPoorEdges(mesh, face_cells, counts.flipped_edges, ctx));
  relaxation.FacesChanged();
  const int after_flips = std::max(1, steps / 2);
  for (int step = 0; step < after_flips; ++step) {
    LSQSURF_RETURN_IF_ERROR(relaxation.Step(step + 1 == after_flips, ctx));
  }
  counts.relaxed_vertices = relaxation.moved();
  return absl::OkStatus();
}

namespace {

// Vertex → incident faces with room for kFlipPasses more faces per vertex: a flip pass adds at
// most one face to a vertex, so the lists are updated in place instead of rebuilt per pass.
class FlipIncidence {
 public:
  explicit FlipIncidence(const core::TriangleMesh& mesh) : count_(mesh.vertices.size(), 0) {
    const size_t n = mesh.vertices.size();
    for (const core::Triangle& t : mesh.faces) {
      for (uint32_t v : t) ++count_[v];
    }
    start_.resize(n + 1, 0);
    for (size_t v = 0; v < n; ++v) start_[v + 1] = start_[v] + count_[v] + kFlipPasses;
    faces_.resize(start_[n]);
    std::fill(count_.begin(), count_.end(), 0);
    for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
      for (uint32_t v : mesh.faces[f]) Add(v, f);
    }
  }
  std::span<const uint32_t> Of(uint32_t v) const { return {faces_.data() + start_[v], count_[v]}; }
  void Add(uint32_t v, uint32_t f) { faces_[start_[v] + count_[v]++] = f; }
  void Remove(uint32_t v, uint32_t f) {
    uint32_t* first = faces_.data() + start_[v];
    uint32_t* last = first + count_[v];
    uint32_t* at = std::find(first, last, f);
    if (at == last) return;
    std::copy(at + 1, last, at);  // Kept in order, so the sweeps see faces as a rebuild would.
    --count_[v];
  }

 private:
  std::vector<uint32_t> start_, count_, faces_;
};

}  // namespace

absl::Status FlipPoorEdges(core::TriangleMesh& mesh, std::vector<uint64_t>* face_cells, int64_t& flips,
                           core::JobContext& ctx) {
  flips = 0;
  const size_t n = mesh.vertices.size();
  const double good_cos = std::cos(kGoodAngleDegrees * std::numbers::pi / 180);
  const double flat_cos = std::cos(kFlipFlatDegrees * std::numbers::pi / 180);
  auto position = [&](uint32_t v) { return mesh.vertices[v].cast<double>(); };
  auto normal_of = [&](const core::Triangle& t) {
    return (position(t[1]) - position(t[0])).cross(position(t[2]) - position(t[0]));
  };
  FlipIncidence incidence(mesh);
  // The faces holding both a and b (in `out`); and whether c and d share an edge already.
  auto faces_with = [&](uint32_t a, uint32_t b, std::vector<uint32_t>& out) {
    out.clear();
    for (uint32_t f : incidence.Of(a)) {
      const core::Triangle& t = mesh.faces[f];
      if (t[0] == b || t[1] == b || t[2] == b) out.push_back(f);
    }
  };
  // The faces a pass looks at: all at first, then only those whose neighbourhood the pass before
  // changed (a face with a flipped vertex, or one whose partner's apex was flipped); the others
  // would be refused again for the same reason.
  std::vector<uint32_t> candidates(mesh.faces.size()), next_candidates;
  for (uint32_t f = 0; f < candidates.size(); ++f) candidates[f] = f;
  std::vector<char> touched(n, 0);
  std::vector<int8_t> longest_edge;
  std::vector<uint32_t> shared, other;
  int64_t first_pass = 0;
  for (int pass = 0; pass < kFlipPasses && !candidates.empty(); ++pass) {
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
    // Each poor face's longest edge, or −1 for a good face.
    longest_edge.resize(candidates.size());
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        candidates.size(), 4096,
        [&](size_t begin, size_t end) {
          for (size_t i = begin; i < end; ++i) {
            longest_edge[i] = PoorTriangleLongestEdge<double>(mesh, mesh.faces[candidates[i]], good_cos);
          }
        },
        &ctx));
    // One flip per vertex per pass: each vertex's incidence list changes at most once a pass.
    std::fill(touched.begin(), touched.end(), 0);
    next_candidates.clear();
    int64_t pass_flips = 0;
    for (size_t i = 0; i < candidates.size(); ++i) {
      const uint32_t f = candidates[i];
      const core::Triangle t = mesh.faces[f];
      if (longest_edge[i] < 0 || touched[t[0]] || touched[t[1]] || touched[t[2]]) continue;
      const auto longest = static_cast<size_t>(longest_edge[i]);
      const uint32_t a = t[longest], b = t[(longest + 1) % 3], c = t[(longest + 2) % 3];
      faces_with(a, b, shared);
      if (shared.size() != 2) continue;  // A border or a non-manifold edge.
      const uint32_t g = shared[0] == f ? shared[1] : shared[0];
      if (face_cells != nullptr && (*face_cells)[g] != (*face_cells)[f]) continue;
      const core::Triangle& s = mesh.faces[g];
      const uint32_t d = s[0] != a && s[0] != b ? s[0] : s[1] != a && s[1] != b ? s[1] : s[2];
      if (touched[d]) {
        next_candidates.push_back(f);
        continue;
      }
      // Only across a flat edge (never a crease), and never onto an edge that exists.
      const Vec3d nf = normal_of(t), ng = normal_of(s);
      if (!(nf.dot(ng) > flat_cos * nf.norm() * ng.norm())) continue;
      faces_with(c, d, other);
      if (!other.empty()) continue;
      const core::Triangle first{a, d, c}, second{d, b, c};
      const Vec3d n1 = normal_of(first), n2 = normal_of(second);
      if (!(n1.dot(nf) > 0 && n2.dot(nf) > 0 && n1.dot(n2) > flat_cos * n1.norm() * n2.norm())) continue;
      const double before = std::min(SmallestAngle(position(a), position(b), position(c)),
                                     SmallestAngle(position(s[0]), position(s[1]), position(s[2])));
      const double after = std::min(SmallestAngle(position(a), position(d), position(c)),
                                    SmallestAngle(position(d), position(b), position(c)));
      if (!(after > before + kFlipGain)) continue;
      mesh.faces[f] = first;
      mesh.faces[g] = second;
      incidence.Remove(a, g), incidence.Remove(b, f), incidence.Add(c, g), incidence.Add(d, f);
      touched[a] = touched[b] = touched[c] = touched[d] = 1;
      ++pass_flips;
    }
    flips += pass_flips;
    // A pass flips each vertex's pairs at most once; later passes find ever fewer.
    if (pass == 0) first_pass = pass_flips;
    if (pass_flips == 0 || pass_flips * kFlipDiminish < first_pass) break;
    for (uint32_t v = 0; v < n; ++v) {
      if (!touched[v]) continue;
      for (uint32_t f : incidence.Of(v)) next_candidates.push_back(f);
    }
    std::sort(next_candidates.begin(), next_candidates.end());
    next_candidates.erase(std::unique(next_candidates.begin(), next_candidates.end()), next_candidates.end());
    std::swap(candidates, next_candidates);
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::extract::internal
