#include "worker/extract/marching_tets.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <optional>

#include "absl/container/flat_hash_set.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/extract/creases.h"
#include "worker/extract/holes.h"
#include "worker/extract/relax.h"

namespace lsqsurf::extract::internal {
namespace {

struct Crossing {
  CornerKey inside_vertex;   // Corner with F < 0.
  CornerKey outside_vertex;  // Corner with F >= 0.
  double inside_value;
  double outside_value;
};

// Edge-connected clusters of a subset of the faces (union-find over faces sharing a side).
class FaceClusters {
 public:
  // Clusters the faces for which `member(f)` holds; calls `on_unshared(lo, hi, f)` for every
  // side (vertex pair lo < hi) that only one member uses.
  template <typename Member, typename Unshared>
  FaceClusters(const std::vector<Triangle>& faces, Member&& member, Unshared&& on_unshared) {
    struct Side {
      uint32_t lo, hi, face;
    };
    std::vector<Side> sides;
    for (uint32_t f = 0; f < faces.size(); ++f) {
      if (!member(f)) continue;
      parent_.emplace(f, f);
      for (int i = 0; i < 3; ++i) {
        const uint32_t a = faces[f][static_cast<size_t>(i)], b = faces[f][static_cast<size_t>((i + 1) % 3)];
        sides.push_back({std::min(a, b), std::max(a, b), f});
      }
    }
    std::sort(sides.begin(), sides.end(),
              [](const Side& x, const Side& y) { return x.lo != y.lo ? x.lo < y.lo : x.hi < y.hi; });
    auto same = [&](size_t i, size_t j) { return sides[i].lo == sides[j].lo && sides[i].hi == sides[j].hi; };
    for (size_t i = 0; i < sides.size(); ++i) {
      const bool same_as_previous = i > 0 && same(i, i - 1);
      if (same_as_previous) parent_[Find(sides[i].face)] = Find(sides[i - 1].face);
      if (!same_as_previous && !(i + 1 < sides.size() && same(i, i + 1))) {
        on_unshared(sides[i].lo, sides[i].hi, sides[i].face);
      }
    }
    for (auto& [face, p] : parent_) ++size_[Find(face)];
  }

  uint32_t Find(uint32_t face) {
    while (parent_[face] != face) face = parent_[face] = parent_[parent_[face]];
    return face;
  }
  int Size(uint32_t root) { return size_[root]; }
  // Calls visit(face, root) for every member.
  template <typename Visit>
  void ForEach(Visit&& visit) {
    for (auto& [face, p] : parent_) visit(face, Find(face));
  }

 private:
  absl::flat_hash_map<uint32_t, uint32_t> parent_;
  absl::flat_hash_map<uint32_t, int> size_;
};

// Marks as trusted again every edge-connected cluster of untrusted triangles with at most
// `max_size` members whose whole border is shared with trusted triangles: such pinholes lie on
// the real surface where the field's confidence dips for a moment (a gap in random sampling),
// and dropping them would open the surface. Large clusters (holes in the data, ghost sheets) and
// clusters that trusted surface does not surround (isolated bubbles and fragments) stay
// untrusted. Returns the triangles restored.
int64_t RestoreSmallPatches(const std::vector<Triangle>& faces, std::vector<char>& trusted, int max_size) {
  if (max_size <= 0) return 0;
  absl::flat_hash_map<uint64_t, uint32_t> border;  // Sides used once among the untrusted: edge → face.
  FaceClusters clusters(
      faces, [&](uint32_t f) { return !trusted[f]; },
      [&](uint32_t lo, uint32_t hi, uint32_t f) { border.emplace(EdgeKey(lo, hi), f); });
  if (border.empty()) return 0;  // No untrusted triangles.
  absl::flat_hash_map<uint32_t, int> open_border;
  for (auto& [edge, face] : border) ++open_border[clusters.Find(face)];
  for (uint32_t f = 0; f < faces.size(); ++f) {
    if (!trusted[f]) continue;
    for (int i = 0; i < 3; ++i) {
      const uint32_t a = faces[f][static_cast<size_t>(i)], b = faces[f][static_cast<size_t>((i + 1) % 3)];
      if (auto it = border.find(EdgeKey(a, b)); it != border.end()) --open_border[clusters.Find(it->second)];
    }
  }
  int64_t restored = 0;
  clusters.ForEach([&](uint32_t face, uint32_t root) {
    // A pinhole has a border, and trusted triangles close every side of it.
    const auto open = open_border.find(root);
    if (clusters.Size(root) <= max_size && open != open_border.end() && open->second == 0) {
      trusted[face] = 1;
      ++restored;
    }
  });
  return restored;
}

// The converse of RestoreSmallPatches: marks as untrusted every edge-connected cluster of at
// most `max_size` trusted triangles that untrusted triangles cut off from the rest of the
// trusted surface (specks left between rejected triangles, joined to the surface by a vertex
// at most). Only the trusted triangles within kSpeckRings vertex rings of an untrusted one are
// examined: a cluster with an edge whose ends both lie farther out may continue into the rest
// of the surface and is kept. Returns the triangles dropped.
constexpr uint8_t kSpeckRings = 6;
int64_t DropCutOffSpecks(const std::vector<Triangle>& faces, std::vector<char>& trusted, size_t num_vertices,
                         int max_size) {
  if (max_size <= 0) return 0;
  constexpr uint8_t kFar = 255;
  std::vector<uint8_t> ring(num_vertices, kFar);  // Vertex rings away from untrusted triangles.
  bool any_untrusted = false;
  for (uint32_t f = 0; f < faces.size(); ++f) {
    if (trusted[f]) continue;
    any_untrusted = true;
    for (uint32_t v : faces[f]) ring[v] = 0;
  }
  if (!any_untrusted) return 0;
  auto nearest_ring = [&](const Triangle& t) { return std::min({ring[t[0]], ring[t[1]], ring[t[2]]}); };
  for (uint8_t k = 0; k < kSpeckRings; ++k) {
    for (uint32_t f = 0; f < faces.size(); ++f) {
      if (!trusted[f] || nearest_ring(faces[f]) != k) continue;
      for (uint32_t v : faces[f]) ring[v] = std::min<uint8_t>(ring[v], static_cast<uint8_t>(k + 1));
    }
  }
  std::vector<uint32_t> escaping;
  FaceClusters clusters(
      faces, [&](uint32_t f) { return trusted[f] && nearest_ring(faces[f]) < kSpeckRings; },
      [&](uint32_t lo, uint32_t hi, uint32_t f) {
        // A triangle beyond the examined rings may share this edge.
        if (ring[lo] >= kSpeckRings && ring[hi] >= kSpeckRings) escaping.push_back(f);
      });
  absl::flat_hash_set<uint32_t> escaping_roots;
  for (uint32_t f : escaping) escaping_roots.insert(clusters.Find(f));
  int64_t dropped = 0;
  clusters.ForEach([&](uint32_t face, uint32_t root) {
    if (clusters.Size(root) <= max_size && !escaping_roots.contains(root)) {
      trusted[face] = 0;
      ++dropped;
    }
  });
  return dropped;
}

// The polygons of the crossed tetrahedra over shared edge crossings. Each polygon is a list of
// crossing indices, oriented so that its normal points from F < 0 to F >= 0 (decided on the
// corner positions; the tetrahedra are never flat).
struct PolygonSoup {
  absl::flat_hash_map<std::pair<CornerKey, CornerKey>, uint32_t> edge_index;
  std::vector<Crossing> crossings;
  std::vector<std::array<uint32_t, 4>> polygons;  // [3] == UINT32_MAX for a triangle.
  std::vector<uint64_t> polygon_cells;            // Where each polygon's tetrahedron lies.
  // Corners moved onto the surface (SnapCorners): they keep their side, so every tetrahedron
  // keeps its signs, and every crossing on their edges is the corner itself (a crossing keyed by
  // the corner twice).
  const absl::flat_hash_map<CornerKey, Vec3d>* snapped = nullptr;

  void Add(const TetCorners& tet, uint64_t cell, const absl::flat_hash_map<CornerKey, FieldValue>& values,
           const std::function<Vec3d(CornerKey)>& position) {
    std::array<FieldValue, 4> corner;
    std::array<int, 4> inside{}, outside{};
    int n_in = 0, n_out = 0;
    for (size_t i = 0; i < 4; ++i) {
      corner[i] = values.at(tet[i]);
      const double v = corner[i].value;
      if (std::isnan(v)) return;
      if (v < 0)
        inside[static_cast<size_t>(n_in++)] = static_cast<int>(i);
      else
        outside[static_cast<size_t>(n_out++)] = static_cast<int>(i);
    }
    if (n_in == 0 || n_out == 0) return;
    std::array<Vec3d, 4> p;
    for (size_t i = 0; i < 4; ++i) p[i] = position(tet[i]);
    auto at = [](auto& array, int i) -> auto& { return array[static_cast<size_t>(i)]; };
    auto edge = [&](int a, int b) {  // a inside, b outside
      CornerKey ka = at(tet, a), kb = at(tet, b);
      if (snapped != nullptr && snapped->contains(kb)) ka = kb;
      if (snapped != nullptr && snapped->contains(ka)) kb = ka;
      auto [it, inserted] = edge_index.try_emplace(std::minmax(ka, kb), static_cast<uint32_t>(crossings.size()));
      if (inserted) crossings.push_back({ka, kb, at(corner, a).value, at(corner, b).value});
      return it->second;
    };
    auto mid = [&](std::pair<int, int> e) { return Vec3d(0.5 * (at(p, e.first) + at(p, e.second))); };
    Vec3d in_c = Vec3d::Zero(), out_c = Vec3d::Zero();
    for (int i = 0; i < n_in; ++i) in_c += at(p, at(inside, i)) / n_in;
    for (int i = 0; i < n_out; ++i) out_c += at(p, at(outside, i)) / n_out;
    const Vec3d outward = out_c - in_c;
    std::array<std::pair<int, int>, 4> ring{};
    int ring_size = 0;
    if (n_in == 1) {
      for (int i = 0; i < 3; ++i) at(ring, ring_size++) = {inside[0], at(outside, i)};
    } else if (n_out == 1) {
      for (int i = 0; i < 3; ++i) at(ring, ring_size++) = {at(inside, i), outside[0]};
    } else {  // Two and two: the crossings form the cycle ac, ad, bd, bc.
      const int a = inside[0], b = inside[1], c = outside[0], d = outside[1];
      ring = {{{a, c}, {a, d}, {b, d}, {b, c}}};
      ring_size = 4;
    }
    const Vec3d p0 = mid(ring[0]), p1 = mid(ring[1]), p2 = mid(ring[2]);
    const bool flip = (p1 - p0).cross(p2 - p0).dot(outward) < 0;
    std::array<uint32_t, 4> poly{UINT32_MAX, UINT32_MAX, UINT32_MAX, UINT32_MAX};
    int size = 0;
    for (int i = 0; i < ring_size; ++i) {
      const auto& e = at(ring, flip ? ring_size - 1 - i : i);
      const uint32_t c = edge(e.first, e.second);
      // A snapped corner ends several ring edges: it enters the polygon once.
      if (size == 0 || (at(poly, size - 1) != c && (i < ring_size - 1 || poly[0] != c))) at(poly, size++) = c;
    }
    if (size >= 3) {
      polygons.push_back(poly);
      polygon_cells.push_back(cell);
    }
  }
};

// Root refinement on the true F along each crossing edge (core::RefineRootOnSegment: regula
// falsi, superlinear, never leaving the bracket). `valid` marks the roots where F is defined.
absl::Status RefineCrossings(const ImplicitFunction& field, const std::vector<Crossing>& crossings,
                             const std::function<Vec3d(CornerKey)>& position, const MarchingOptions& params,
                             TriangleMesh& mesh, std::vector<char>& valid, JobContext& ctx) {
  mesh.vertices.resize(crossings.size());
  // Creases and relaxation need them.
  const bool normals = params.vertex_normals || params.crease_angle > 0 || params.relax_steps > 0;
  if (normals) mesh.normals.resize(crossings.size());
  valid.assign(crossings.size(), 0);
  return core::ParallelFor(
      crossings.size(), 256,
      [&](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) {
          const Crossing& c = crossings[i];
          const Vec3d a = position(c.inside_vertex), b = position(c.outside_vertex);
          Vec3d x = b;  // A snapped corner is its own crossing.
          if (c.inside_vertex != c.outside_vertex) {
            double t = core::RefineRootOnSegment(field, a, b, c.inside_value, c.outside_value, params.refine_steps);
            // Keep vertices strictly inside their edge: coincident vertices would make
            // zero-area triangles that some decoders drop.
            t = std::clamp(t, 1e-4, 1.0 - 1e-4);
            x = a + t * (b - a);
          }
          mesh.vertices[i] = x.cast<float>();
          // A root where F is not trustworthy (e.g. an iaMLS ghost sheet, or a sign-only
          // extension of F across a hole in the data) is no surface: drop what uses it.
          const FieldGradient g = field.ValueAndGradient(x);
          valid[i] = g.defined;
          if (normals) {
            const double len = g.gradient.norm();
            mesh.normals[i] =
                len > 0 ? Vec3f((g.gradient / len).cast<float>()) : Vec3f((b - a).normalized().cast<float>());
          }
        }
      },
      &ctx, [&](double f) { ctx.ReportProgress("", 0.9 * f); });
}

// Triangles of the polygons (quads split along the shorter diagonal), each marked trusted when
// every vertex is valid; `face_cells` (when tracing) gets each triangle's polygon's cell.
void Triangulate(const PolygonSoup& soup, const std::vector<char>& valid, TriangleMesh& mesh,
                 std::vector<char>& face_trusted, std::vector<uint64_t>* face_cells, IsosurfaceStats& stats) {
  const auto& polygons = soup.polygons;
  mesh.faces.reserve(polygons.size() * 3 / 2);
  face_trusted.reserve(polygons.size() * 3 / 2);
  for (size_t k = 0; k < polygons.size(); ++k) {
    const auto& p = polygons[k];
    const bool trusted = valid[p[0]] && valid[p[1]] && valid[p[2]] && (p[3] == UINT32_MAX || valid[p[3]]);
    const size_t before = mesh.faces.size();
    if (p[3] == UINT32_MAX) {
      mesh.faces.push_back({p[0], p[1], p[2]});
    } else {
      const float d02 = (mesh.vertices[p[0]] - mesh.vertices[p[2]]).squaredNorm();
      const float d13 = (mesh.vertices[p[1]] - mesh.vertices[p[3]]).squaredNorm();
      if (d02 <= d13) {
        mesh.faces.push_back({p[0], p[1], p[2]});
        mesh.faces.push_back({p[0], p[2], p[3]});
      } else {
        mesh.faces.push_back({p[0], p[1], p[3]});
        mesh.faces.push_back({p[1], p[2], p[3]});
      }
    }
    face_trusted.resize(mesh.faces.size(), trusted);
    if (face_cells != nullptr) face_cells->resize(mesh.faces.size(), soup.polygon_cells[k]);
    if (!trusted) stats.rejected_polygons += static_cast<int64_t>(mesh.faces.size() - before);
  }
}

}  // namespace

absl::Status CornerValues::Evaluate(const ImplicitFunction& field, const std::function<Vec3d(CornerKey)>& position,
                                    IsosurfaceStats& stats, JobContext& ctx) {
  pending_positions_.resize(pending_.size());
  pending_values_.resize(pending_.size());
  for (size_t i = 0; i < pending_.size(); ++i) pending_positions_[i] = position(pending_[i]);
  LSQSURF_RETURN_IF_ERROR(field.ValueOnlyBatch(pending_positions_, pending_values_, &ctx));
  for (size_t i = 0; i < pending_.size(); ++i) values_[pending_[i]] = FieldValue{pending_values_[i], false};
  stats.field_evaluations += static_cast<int64_t>(pending_.size());
  pending_.clear();
  return absl::OkStatus();
}

// Mesh enhancement (METHODS §1.9, after Dietrich et al.'s edge transformations): marching puts
// a vertex near every corner that the surface passes close to, and the triangles there are
// slivers. Such a corner (a crossing within `share` of an incident crossed edge from it) is moved
// onto the surface by Newton steps along ∇F instead, where that moves it less than `share` of its
// shortest edge and flips or flattens none of its tetrahedra; the crossings on its edges then
// merge into it. It keeps its sign, so every tetrahedron keeps its sign pattern: the surface
// followers' choice of tetrahedra stays right. Returns the moved corners and their positions.
absl::flat_hash_map<CornerKey, Vec3d> SnapCorners(const ImplicitFunction& field,
                                                  const std::function<void(const TetVisitor&)>& for_each_tet,
                                                  const absl::flat_hash_map<CornerKey, FieldValue>& values,
                                                  const std::function<Vec3d(CornerKey)>& position, double share,
                                                  JobContext& ctx) {
  struct Near {
    double share = 1;                                           // Of the nearest crossing along an incident edge.
    double shortest = std::numeric_limits<double>::infinity();  // Incident edge of a crossed tetrahedron.
  };
  absl::flat_hash_map<CornerKey, Near> near;
  for_each_tet([&](const TetCorners& tet, uint64_t) {
    std::array<double, 4> f;
    bool negative = false, positive = false;
    for (size_t i = 0; i < 4; ++i) {
      f[i] = values.at(tet[i]).value;  // Sign-only values: `defined` is decided at the roots.
      if (std::isnan(f[i])) return;
      (f[i] < 0 ? negative : positive) = true;
    }
    if (!negative || !positive) return;
    std::array<Vec3d, 4> p;
    std::array<Near*, 4> entry;
    for (size_t i = 0; i < 4; ++i) near.try_emplace(tet[i]);
    for (size_t i = 0; i < 4; ++i) {
      p[i] = position(tet[i]);
      entry[i] = &near.at(tet[i]);  // Taken after every insertion: a rehash would move them.
    }
    for (size_t i = 0; i < 4; ++i) {
      for (size_t j = i + 1; j < 4; ++j) {
        const double length = (p[i] - p[j]).norm();
        Near& a = *entry[i];
        Near& b = *entry[j];
        a.shortest = std::min(a.shortest, length);
        b.shortest = std::min(b.shortest, length);
        if ((f[i] < 0) == (f[j] < 0)) continue;
        const double t = f[i] / (f[i] - f[j]);
        a.share = std::min(a.share, t);
        b.share = std::min(b.share, 1 - t);
      }
    }
  });
  std::vector<std::pair<CornerKey, Vec3d>> moves;
  for (const auto& [key, n] : near) {
    if (n.share < share) moves.push_back({key, Vec3d::Zero()});
  }
  std::vector<char> accepted(moves.size(), 0);
  (void)core::ParallelFor(
      moves.size(), 256,
      [&](size_t begin, size_t end) {
        for (size_t k = begin; k < end; ++k) {
          const Vec3d start = position(moves[k].first);
          Vec3d x = start;
          FieldGradient g;
          for (int step = 0; step < 3; ++step) {
            g = field.ValueAndGradient(x);
            const double slope2 = g.gradient.squaredNorm();
            if (!g.defined || !(slope2 > 0)) break;
            x -= (g.value / slope2) * g.gradient;
          }
          g = field.ValueAndGradient(x);
          moves[k].second = x;
          accepted[k] = g.defined && (x - start).norm() < share * near.at(moves[k].first).shortest &&
                        std::abs(g.value) < 1e-3 * share * near.at(moves[k].first).shortest;
        }
      },
      &ctx);
  absl::flat_hash_map<CornerKey, Vec3d> snapped;
  for (size_t k = 0; k < moves.size(); ++k) {
    if (accepted[k]) snapped.emplace(moves[k].first, moves[k].second);
  }
  // No tetrahedron may turn over or flatten (below a tenth of its volume): its moved corners stay.
  // A crossed edge keeps at most one moved end (the nearer to its crossing), which its crossing
  // then is.
  for (int pass = 0; pass < 3 && !snapped.empty(); ++pass) {
    std::vector<CornerKey> undo;
    for_each_tet([&](const TetCorners& tet, uint64_t) {
      for (size_t i = 0; i < 4; ++i) {
        for (size_t j = i + 1; j < 4; ++j) {
          if ((values.at(tet[i]).value < 0) == (values.at(tet[j]).value < 0)) continue;
          if (!snapped.contains(tet[i]) || !snapped.contains(tet[j])) continue;
          undo.push_back(near.at(tet[i]).share > near.at(tet[j]).share ? tet[i] : tet[j]);
        }
      }
      std::array<Vec3d, 4> before, after;
      bool moved = false;
      for (size_t i = 0; i < 4; ++i) {
        before[i] = position(tet[i]);
        const auto it = snapped.find(tet[i]);
        moved |= it != snapped.end();
        after[i] = it != snapped.end() ? it->second : before[i];
      }
      if (!moved) return;
      auto volume = [](const std::array<Vec3d, 4>& q) { return (q[1] - q[0]).cross(q[2] - q[0]).dot(q[3] - q[0]); };
      const double v0 = volume(before), v1 = volume(after);
      if (v1 * v0 <= 0 || std::abs(v1) < 0.1 * std::abs(v0)) {
        for (CornerKey k : tet) {
          if (snapped.contains(k)) undo.push_back(k);
        }
      }
    });
    if (undo.empty()) break;
    for (CornerKey k : undo) snapped.erase(k);
  }
  return snapped;
}

void CornerValues::CountInside(const absl::flat_hash_map<CornerKey, Vec3d>& corners) {
  // The smallest negative value: the sign says inside (their crossings are their own places).
  for (const auto& [key, on_surface] : corners) values_.at(key).value = -std::numeric_limits<double>::denorm_min();
}

// Where Newton steps along ∇F take a corner that lies just outside, if they converge.
std::optional<Vec3d> OntoSurface(const ImplicitFunction& field, const Vec3d& corner, double start_value) {
  constexpr int kSteps = 6;
  Vec3d x = corner;
  for (int step = 0; step < kSteps; ++step) {
    const FieldGradient g = field.ValueAndGradientOnly(x);
    const double slope2 = g.gradient.squaredNorm();
    if (!(slope2 > 0) || !std::isfinite(g.value)) return std::nullopt;
    x -= (g.value / slope2) * g.gradient;
  }
  if (!(std::abs(field.ValueOnly(x)) <= 0.01 * start_value)) return std::nullopt;
  return x;
}

absl::StatusOr<absl::flat_hash_map<CornerKey, Vec3d>> PiercedCorners(
    const ImplicitFunction& field, const std::function<void(const TetVisitor&)>& for_each_tet,
    const absl::flat_hash_map<CornerKey, FieldValue>& values, const std::function<Vec3d(CornerKey)>& position,
    JobContext& ctx) {
  absl::flat_hash_set<std::pair<CornerKey, CornerKey>> candidates;
  for_each_tet([&](const TetCorners& tet, uint64_t) {
    std::array<double, 4> f;
    for (size_t i = 0; i < 4; ++i) f[i] = values.at(tet[i]).value;
    for (size_t i = 0; i < 4; ++i) {
      for (size_t j = i + 1; j < 4; ++j) {
        if (!(f[i] >= 0 && f[j] >= 0)) continue;  // NaN fails too.
        const double bound = kPiercedShare * (position(tet[i]) - position(tet[j])).norm();
        if (f[i] < bound && f[j] < bound) candidates.insert(std::minmax(tet[i], tet[j]));
      }
    }
  });
  std::vector<std::pair<CornerKey, CornerKey>> edges(candidates.begin(), candidates.end());
  std::sort(edges.begin(), edges.end());  // The hash set's order is not the same from run to run.
  std::vector<Vec3d> midpoints(edges.size());
  for (size_t k = 0; k < edges.size(); ++k) midpoints[k] = 0.5 * (position(edges[k].first) + position(edges[k].second));
  std::vector<double> mid_values(edges.size());
  LSQSURF_RETURN_IF_ERROR(field.ValueOnlyBatch(midpoints, mid_values, &ctx));
  absl::flat_hash_map<CornerKey, Vec3d> pierced;
  absl::flat_hash_map<CornerKey, std::optional<Vec3d>> projected;  // Once per corner.
  for (size_t k = 0; k < edges.size(); ++k) {
    if (!(mid_values[k] < 0)) continue;
    const auto [a, b] = edges[k];
    const double reach = kPiercedReach * (position(a) - position(b)).norm();
    bool reached = true;
    for (CornerKey end : {a, b}) {
      auto [at, fresh] = projected.try_emplace(end);
      if (fresh) at->second = OntoSurface(field, position(end), values.at(end).value);
      reached = reached && at->second && (*at->second - position(end)).norm() <= reach;
    }
    if (!reached) continue;
    pierced.try_emplace(a, *projected.at(a));
    pierced.try_emplace(b, *projected.at(b));
  }
  return pierced;
}

uint64_t LatticeEdgeHash(CornerKey a, CornerKey b) {
  if (a > b) std::swap(a, b);
  // splitmix64's finaliser over both keys: distinct edges collide with probability ~2^-64.
  const uint64_t h = core::Mix64(a * 0x9E3779B97F4A7C15ull + b);
  return h == 0 ? 1 : h;
}

absl::StatusOr<IsosurfaceResult> MarchTetrahedra(const ImplicitFunction& field,
                                                 const std::function<void(const TetVisitor&)>& for_each_tet,
                                                 const absl::flat_hash_map<CornerKey, FieldValue>& values,
                                                 const std::function<Vec3d(CornerKey)>& position,
                                                 const MarchingOptions& params, const IsosurfaceStats& tracking,
                                                 JobContext& ctx,
                                                 const absl::flat_hash_map<CornerKey, Vec3d>* pierced) {
  IsosurfaceResult result;
  result.stats = tracking;
  IsosurfaceStats& stats = result.stats;
  auto stage_start = std::chrono::steady_clock::now();
  absl::flat_hash_map<CornerKey, Vec3d> snapped;
  if (params.snap_share > 0) {
    snapped = SnapCorners(field, for_each_tet, values, position, params.snap_share, ctx);
    stats.snapped_corners = static_cast<int64_t>(snapped.size());
  }
  // Pierced corners are their own crossings, as snapped ones are (they count inside, so no edge
  // between them and a snapped one is crossed).
  if (pierced != nullptr) snapped.insert(pierced->begin(), pierced->end());
  const std::function<Vec3d(CornerKey)> moved_position = [&](CornerKey k) {
    const auto it = snapped.find(k);
    return it != snapped.end() ? it->second : position(k);
  };
  PolygonSoup soup;
  soup.snapped = &snapped;
  for_each_tet([&](const TetCorners& tet, uint64_t cell) {
    ++stats.tetrahedra;
    soup.Add(tet, cell, values, moved_position);
  });
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  TriangleMesh& mesh = result.mesh;
  std::vector<char> valid;
  LSQSURF_RETURN_IF_ERROR(RefineCrossings(field, soup.crossings, moved_position, params, mesh, valid, ctx));
  SurfaceTrace& trace = result.trace;
  if (params.trace) {
    trace.vertex_edges.resize(soup.crossings.size());
    for (size_t i = 0; i < soup.crossings.size(); ++i) {
      trace.vertex_edges[i] = LatticeEdgeHash(soup.crossings[i].inside_vertex, soup.crossings[i].outside_vertex);
    }
  }
  std::vector<char> face_trusted;
  Triangulate(soup, valid, mesh, face_trusted, params.trace ? &trace.face_cells : nullptr, stats);
  stats.restored_triangles = RestoreSmallPatches(mesh.faces, face_trusted, params.max_patch_triangles);
  stats.rejected_polygons -= stats.restored_triangles;
  stats.rejected_polygons +=
      DropCutOffSpecks(mesh.faces, face_trusted, mesh.vertices.size(), params.max_patch_triangles);
  KeepFaces(face_trusted, mesh, trace);
  if (params.max_hole_edges > 0 && !params.trace) stats.filled_holes = FillSmallHoles(mesh, params.max_hole_edges);
  stats.crossings = static_cast<int64_t>(mesh.vertices.size());
  stats.marching_seconds = core::SecondsSince(stage_start);
  ctx.ReportProgress("", 1.0);
  return result;
}

absl::Status FinishSurface(const ImplicitFunction& field, const MarchingOptions& params, IsosurfaceResult& result,
                           JobContext& ctx, std::span<const char> fixed) {
  IsosurfaceStats& stats = result.stats;
  TriangleMesh& mesh = result.mesh;
  auto stage_start = std::chrono::steady_clock::now();
  if (params.crease_angle > 0) {
    CreaseCounts creases;
    const bool traced = !result.trace.face_cells.empty();
    LSQSURF_RETURN_IF_ERROR(SharpenCreases(field, params.crease_angle, mesh, creases, ctx, fixed,
                                           traced ? &result.trace.face_cells : nullptr));
    if (traced) result.trace.vertex_edges.resize(mesh.vertices.size(), 0);
    stats.crease_vertices = creases.crease_vertices;
    stats.crease_corners = creases.corners;
    stats.crease_snapped = creases.snapped_vertices;
  }
  stats.crease_seconds = core::SecondsSince(stage_start);
  stage_start = std::chrono::steady_clock::now();
  if (params.relax_steps > 0) {
    const bool traced = !result.trace.face_cells.empty();
    EnhanceCounts counts;
    LSQSURF_RETURN_IF_ERROR(EnhanceTriangles(field, params.relax_steps, static_cast<uint32_t>(stats.crossings), mesh,
                                             traced ? &result.trace.face_cells : nullptr, counts, ctx));
    stats.relaxed_vertices = counts.relaxed_vertices;
    stats.flipped_edges = counts.flipped_edges;
  }
  stats.relax_seconds = core::SecondsSince(stage_start);
  if (!params.vertex_normals) mesh.normals.clear();
  return absl::OkStatus();
}

}  // namespace lsqsurf::extract::internal
