#include "worker/extract/relax.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <vector>

#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/extract/marching_tets.h"

namespace lsqsurf::extract::internal {
namespace {

using core::Vec3d;
using core::Vec3f;

// Share of the way to the neighbours' mean taken per step.
constexpr double kStepShare = 0.5;
// A tangential move that ends farther than this share of the mean edge from F = 0 is not made
// (the surface bends too much there for one Newton step).
constexpr double kMaxOffsetShare = 0.1;
// A move is not made where the normal would turn by more than about 25° (onto another sheet).
constexpr double kSameSheetCos = 0.9;
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

// Vertex → incident faces as compressed rows: the faces of v are incident[start[v] .. start[v + 1]).
void IncidentFaces(const core::TriangleMesh& mesh, std::vector<uint32_t>& start, std::vector<uint32_t>& incident) {
  start.assign(mesh.vertices.size() + 1, 0);
  incident.resize(3 * mesh.faces.size());
  for (const core::Triangle& t : mesh.faces) {
    for (uint32_t v : t) ++start[v + 1];
  }
  for (size_t v = 0; v < mesh.vertices.size(); ++v) start[v + 1] += start[v];
  std::vector<uint32_t> cursor(start.begin(), start.end() - 1);
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    for (uint32_t v : mesh.faces[f]) incident[cursor[v]++] = f;
  }
}

// The vertices that stay where they are: from `first_fixed` on (crease splits), on an unsplit
// crease, and on a border.
absl::Status MarkFixedVertices(const core::TriangleMesh& mesh, const std::vector<uint32_t>& start,
                               const std::vector<uint32_t>& incident, uint32_t first_fixed, std::vector<char>& fixed,
                               core::JobContext& ctx) {
  const size_t n = mesh.vertices.size();
  fixed.assign(n, 0);
  for (size_t v = first_fixed; v < n; ++v) fixed[v] = 1;
  // Vertices on a crease that was not split (an edge between two marching vertices whose normals
  // differ by more than about 25°): one that lies on the crease line would slide off it.
  for (const core::Triangle& t : mesh.faces) {
    for (size_t i = 0; i < 3; ++i) {
      const uint32_t a = t[i], b = t[(i + 1) % 3];
      if (a < first_fixed && b < first_fixed && mesh.normals[a].dot(mesh.normals[b]) < kSameSheetCos) {
        fixed[a] = fixed[b] = 1;
      }
    }
  }
  // Vertices on an edge without exactly two faces (a border): each vertex counts the other ends
  // of its faces' edges through it, every edge appearing once per face.
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        std::vector<uint32_t> ends;
        for (size_t v = begin; v < end; ++v) {
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
            if (j - i != 2) fixed[v] = 1;
            i = j;
          }
        }
      },
      &ctx));
  return absl::OkStatus();
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

}  // namespace

absl::Status RelaxTangentially(const core::ImplicitFunction& field, int steps, uint32_t first_fixed,
                               core::TriangleMesh& mesh, int64_t& moves, core::JobContext& ctx) {
  const size_t n = mesh.vertices.size();
  std::vector<uint32_t> start, incident;
  IncidentFaces(mesh, start, incident);
  std::vector<char> fixed;
  LSQSURF_RETURN_IF_ERROR(MarkFixedVertices(mesh, start, incident, first_fixed, fixed, ctx));
  std::vector<Vec3f> next(mesh.vertices), next_normals(mesh.normals);
  std::vector<char> moved(n, 0);
  std::vector<char> poor(mesh.faces.size());
  const double good_cos = std::cos(kGoodAngleDegrees * std::numbers::pi / 180);
  for (int step = 0; step < steps; ++step) {
    // Poorly shaped triangles: an angle of less than kGoodAngleDegrees. Their vertices move.
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        mesh.faces.size(), 4096,
        [&](size_t begin, size_t end) {
          for (size_t f = begin; f < end; ++f) {
            const core::Triangle& t = mesh.faces[f];
            poor[f] = 0;
            for (size_t i = 0; i < 3; ++i) {
              const Vec3f u = mesh.vertices[t[(i + 1) % 3]] - mesh.vertices[t[i]];
              const Vec3f w = mesh.vertices[t[(i + 2) % 3]] - mesh.vertices[t[i]];
              if (u.dot(w) > good_cos * u.norm() * w.norm()) poor[f] = 1;
            }
          }
        },
        &ctx));
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        n, 512,
        [&](size_t begin, size_t end) {
          for (size_t v = begin; v < end; ++v) {
            next[v] = mesh.vertices[v];
            next_normals[v] = mesh.normals[v];
            if (fixed[v] || start[v] == start[v + 1]) continue;
            bool needs = false;
            for (uint32_t k = start[v]; k < start[v + 1] && !needs; ++k) needs = poor[incident[k]] != 0;
            if (!needs) continue;
            const Vec3d p = mesh.vertices[v].cast<double>(), normal = mesh.normals[v].cast<double>();
            Vec3d mean = Vec3d::Zero();
            double edge = 0;
            int count = 0;
            for (uint32_t k = start[v]; k < start[v + 1]; ++k) {
              for (uint32_t w : mesh.faces[incident[k]]) {
                if (w == v) continue;
                mean += mesh.vertices[w].cast<double>();
                edge += (mesh.vertices[w].cast<double>() - p).norm();
                ++count;
              }
            }
            mean /= count;
            edge /= count;
            Vec3d delta = kStepShare * (mean - p);
            delta -= normal.dot(delta) * normal;
            Vec3d x = p + delta;
            // One Newton step back onto F = 0: the tangential move leaves x within a small share
            // of an edge of the surface, where one step leaves an error of second order.
            const core::FieldGradient g = field.ValueAndGradientOnly(x);
            const double slope2 = g.gradient.squaredNorm();
            if (!g.defined || !(slope2 > 0) || !(std::abs(g.value) <= kMaxOffsetShare * edge)) continue;
            // A vertex beside a crease must stay on its side of it: no move where ∇F turns.
            if (g.gradient.dot(normal) < kSameSheetCos * std::sqrt(slope2)) continue;
            x -= (g.value / slope2) * g.gradient;
            // None of its triangles may turn over.
            bool folds = false;
            for (uint32_t k = start[v]; k < start[v + 1] && !folds; ++k) {
              const core::Triangle& t = mesh.faces[incident[k]];
              std::array<Vec3d, 3> q, q_new;
              for (size_t i = 0; i < 3; ++i) {
                q[i] = mesh.vertices[t[i]].cast<double>();
                q_new[i] = t[i] == v ? x : q[i];
              }
              const Vec3d before = (q[1] - q[0]).cross(q[2] - q[0]),
                          after = (q_new[1] - q_new[0]).cross(q_new[2] - q_new[0]);
              folds = before.dot(after) <= 0;
            }
            if (folds) continue;
            next[v] = x.cast<float>();
            next_normals[v] = g.gradient.normalized().cast<float>();
            moved[v] = 1;
          }
        },
        &ctx));
    std::swap(mesh.vertices, next);
    std::swap(mesh.normals, next_normals);
  }
  moves = 0;
  for (char m : moved) moves += m;
  return absl::OkStatus();
}

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
  std::vector<uint32_t> start, incident;
  int64_t first_pass = 0;
  for (int pass = 0; pass < kFlipPasses; ++pass) {
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
    // Rebuilt per pass: flips change it.
    IncidentFaces(mesh, start, incident);
    // The faces holding both a and b (in `out`); and whether c and d share an edge already.
    auto faces_with = [&](uint32_t a, uint32_t b, std::vector<uint32_t>& out) {
      out.clear();
      for (uint32_t k = start[a]; k < start[a + 1]; ++k) {
        const core::Triangle& t = mesh.faces[incident[k]];
        if (t[0] == b || t[1] == b || t[2] == b) out.push_back(incident[k]);
      }
    };
    // Each poor face's longest edge (opposite its largest angle: the one a flip can shorten), or
    // −1 for a good face.
    std::vector<int8_t> longest_edge(mesh.faces.size(), -1);
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        mesh.faces.size(), 4096,
        [&](size_t begin, size_t end) {
          for (size_t f = begin; f < end; ++f) {
            const core::Triangle& t = mesh.faces[f];
            int8_t longest = 0;
            double longest2 = -1;
            bool poor = false;
            for (size_t i = 0; i < 3; ++i) {
              const Vec3d u = position(t[(i + 1) % 3]) - position(t[i]), w = position(t[(i + 2) % 3]) - position(t[i]);
              poor |= u.dot(w) > good_cos * u.norm() * w.norm();
              if (u.squaredNorm() > longest2) longest2 = u.squaredNorm(), longest = static_cast<int8_t>(i);
            }
            if (poor) longest_edge[f] = longest;
          }
        },
        &ctx));
    // One flip per vertex per pass: the incidence lists of the vertices not yet touched stay right.
    std::vector<char> touched(n, 0);
    std::vector<uint32_t> shared, other;
    int64_t pass_flips = 0;
    for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
      const core::Triangle t = mesh.faces[f];
      if (longest_edge[f] < 0 || touched[t[0]] || touched[t[1]] || touched[t[2]]) continue;
      const auto longest = static_cast<size_t>(longest_edge[f]);
      const uint32_t a = t[longest], b = t[(longest + 1) % 3], c = t[(longest + 2) % 3];
      faces_with(a, b, shared);
      if (shared.size() != 2) continue;  // A border or a non-manifold edge.
      const uint32_t g = shared[0] == f ? shared[1] : shared[0];
      if (face_cells != nullptr && (*face_cells)[g] != (*face_cells)[f]) continue;
      const core::Triangle& s = mesh.faces[g];
      const uint32_t d = s[0] != a && s[0] != b ? s[0] : s[1] != a && s[1] != b ? s[1] : s[2];
      if (touched[d]) continue;
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
      touched[a] = touched[b] = touched[c] = touched[d] = 1;
      ++pass_flips;
    }
    flips += pass_flips;
    // A pass flips each vertex's pairs at most once; later passes find ever fewer.
    if (pass == 0) first_pass = pass_flips;
    if (pass_flips == 0 || pass_flips * kFlipDiminish < first_pass) break;
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::extract::internal
