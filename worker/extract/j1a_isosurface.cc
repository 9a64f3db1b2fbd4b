#include "worker/extract/j1a_isosurface.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <iterator>
#include <limits>
#include <optional>
#include <string>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/extract/marching_tets.h"

namespace lsqsurf::extract {

SurfaceBand MarkSurfaceBand(const AdaptiveOctree& tree, std::span<const Vec3f> points, int level) {
  SurfaceBand band;
  const int64_t n = int64_t{1} << level;
  for (const Vec3f& p : points) band.occupied.insert(CellKey(tree.CellAt(level, p.cast<double>())));
  for (uint64_t key : band.occupied) {
    const OctreeCell c = CellFromKey(key);
    for (int d = 0; d < 27; ++d) {
      const int64_t x = int64_t{c.x} + d % 3 - 1, y = int64_t{c.y} + (d / 3) % 3 - 1, z = int64_t{c.z} + d / 9 - 1;
      if (x < 0 || y < 0 || z < 0 || x >= n || y >= n || z >= n) continue;
      for (int l = level - 1; l >= 0; --l) {
        const int shift = level - l;
        if (!band.ancestors
                 .insert(CellKey({l, static_cast<uint32_t>(x >> shift), static_cast<uint32_t>(y >> shift),
                                  static_cast<uint32_t>(z >> shift)}))
                 .second) {
          break;  // Its ancestors are in already.
        }
      }
    }
  }
  return band;
}

double EstimateChordError(const ImplicitFunction& field, const Vec3d& centre, double edge) {
  constexpr double kInfinite = std::numeric_limits<double>::infinity();
  // J1a tetrahedra have edges of 0.5 to 0.87 cell edges; the triangles cut from them are shorter.
  constexpr double kChordShare = 0.5;
  const FieldGradient at_centre = field.ValueAndGradientOnly(centre);
  const double g2 = at_centre.gradient.squaredNorm();
  if (!std::isfinite(at_centre.value) || !(g2 > 0) || !std::isfinite(g2)) return kInfinite;
  // One Newton step towards the surface, at most a cell edge.
  Vec3d step = -at_centre.value * at_centre.gradient / g2;
  if (const double length = step.norm(); length > edge) step *= edge / length;
  const Vec3d p = centre + step;
  const Vec3d normal = at_centre.gradient / std::sqrt(g2);
  const Vec3d u = normal.unitOrthogonal(), v = normal.cross(u);
  const double half = edge / 2;
  double turn = 0;
  for (const Vec3d& t : {u, v}) {
    const Vec3d a = field.ValueAndGradientOnly(p + half * t).gradient;
    const Vec3d b = field.ValueAndGradientOnly(p - half * t).gradient;
    const double na = a.norm(), nb = b.norm();
    if (!(na > 0 && nb > 0) || !std::isfinite(na * nb)) return kInfinite;
    turn = std::max(turn, std::acos(std::clamp(a.dot(b) / (na * nb), -1.0, 1.0)));
  }
  const double curvature = turn / edge;
  const double chord = kChordShare * edge;
  return curvature * chord * chord / 8;
}

absl::Status RefineSurfaceBand(AdaptiveOctree& tree, const SurfaceBand& coarse, int coarse_level,
                               const SurfaceBand& fine, const std::function<bool(const OctreeCell&)>& wants_finer,
                               JobContext& ctx) {
  // Decide level by level, in parallel: the decisions are the expensive part (field
  // evaluations); the tree itself is then split serially.
  absl::flat_hash_set<uint64_t> split;
  std::vector<OctreeCell> level_cells;
  for (uint64_t key : fine.ancestors) {
    if (const OctreeCell c = CellFromKey(key); c.level == coarse_level) level_cells.push_back(c);
  }
  std::vector<char> decision;
  while (!level_cells.empty()) {
    decision.assign(level_cells.size(), 0);
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        level_cells.size(), 64,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i) decision[i] = wants_finer(level_cells[i]) ? 1 : 0;
        },
        &ctx));
    std::vector<OctreeCell> next;
    for (size_t i = 0; i < level_cells.size(); ++i) {
      if (!decision[i]) continue;
      const OctreeCell& c = level_cells[i];
      split.insert(CellKey(c));
      for (uint32_t k = 0; k < 8; ++k) {
        const OctreeCell child{c.level + 1, 2 * c.x + (k & 1), 2 * c.y + ((k >> 1) & 1), 2 * c.z + ((k >> 2) & 1)};
        if (fine.ancestors.contains(CellKey(child))) next.push_back(child);
      }
    }
    level_cells = std::move(next);
  }
  tree.Refine([&](const OctreeCell& c) {
    const uint64_t key = CellKey(c);
    return (c.level < coarse_level && coarse.ancestors.contains(key)) || split.contains(key);
  });
  return absl::OkStatus();
}

namespace {

// The leaf whose cube holds `p` (clamped into the root), or nullptr.
const OctreeCell* LeafHolding(const AdaptiveOctree& tree, const Vec3f& p) {
  return tree.LeafContaining(tree.CellAt(tree.max_depth(), p.cast<double>()));
}

struct LeafWork {
  std::vector<TetKeys> tets;          // All tetrahedra; after the sign test, the crossed ones.
  std::vector<VertexKey> corners;     // Distinct corners, sorted.
  std::vector<uint8_t> corner_signs;  // Per corner: 1 negative, 2 not negative, 0 unknown (NaN).
  std::vector<OctreeCell> neighbors;  // Leaves touching a crossed leaf.
};

// Keeps the leaf's tetrahedra that the surface crosses and, when there are any, lists the
// leaves it may continue into (every leaf touching this one). Reads only the tree and `values`.
void KeepCrossedTetrahedra(const AdaptiveOctree& tree, const absl::flat_hash_map<VertexKey, FieldValue>& values,
                           const OctreeCell& leaf, LeafWork& w) {
  w.neighbors.clear();
  // One lookup in the shared map per distinct corner; the tetrahedra then read the leaf's own
  // sorted list (a few dozen entries, in cache).
  w.corner_signs.resize(w.corners.size());
  for (size_t i = 0; i < w.corners.size(); ++i) {
    const double v = values.find(w.corners[i])->second.value;
    w.corner_signs[i] = std::isnan(v) ? 0 : (v < 0 ? 1 : 2);
  }
  size_t kept = 0;
  for (const TetKeys& t : w.tets) {
    uint8_t signs = 0;
    for (VertexKey k : t) {
      signs |= w.corner_signs[static_cast<size_t>(std::lower_bound(w.corners.begin(), w.corners.end(), k) -
                                                  w.corners.begin())];
    }
    if (signs == 3) w.tets[kept++] = t;
  }
  w.tets.resize(kept);
  if (kept == 0) return;
  const int64_t cells = int64_t{1} << leaf.level;
  for (int d = 0; d < 27; ++d) {
    const int64_t x = int64_t{leaf.x} + d % 3 - 1, y = int64_t{leaf.y} + (d / 3) % 3 - 1,
                  z = int64_t{leaf.z} + d / 9 - 1;
    if (d == 13 || x < 0 || y < 0 || z < 0 || x >= cells || y >= cells || z >= cells) continue;
    const OctreeCell probe{leaf.level, static_cast<uint32_t>(x), static_cast<uint32_t>(y), static_cast<uint32_t>(z)};
    if (const OctreeCell* other = tree.LeafContaining(probe)) {
      w.neighbors.push_back(*other);
    } else {  // Finer: in a balanced tree its children are leaves.
      for (uint32_t c = 0; c < 8; ++c) {
        const OctreeCell child{leaf.level + 1, 2 * probe.x + (c & 1), 2 * probe.y + ((c >> 1) & 1),
                               2 * probe.z + ((c >> 2) & 1)};
        if (tree.IsLeaf(child)) w.neighbors.push_back(child);
      }
    }
  }
}

// Corners counted inside after the surface was followed (PiercedCorners) make crossed
// tetrahedra of some that had every corner outside. Every leaf holding such a corner touches the
// crossed leaf it was found in, so it was visited: their tetrahedra about the corners are looked at
// again and the newly crossed ones added.
absl::Status AddTetrahedraCrossedAt(const AdaptiveOctree& tree, const absl::flat_hash_set<uint64_t>& visited,
                                    const absl::flat_hash_map<VertexKey, Vec3d>& pierced,
                                    const absl::flat_hash_map<VertexKey, FieldValue>& values,
                                    std::vector<TetKeys>& crossed_tets, std::vector<uint64_t>* crossed_cells,
                                    JobContext& ctx) {
  std::vector<uint64_t> leaves(visited.begin(), visited.end());
  std::sort(leaves.begin(), leaves.end());  // The same order in every run.
  std::vector<std::vector<TetKeys>> found(leaves.size());
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      leaves.size(), 256,
      [&](size_t b, size_t e) {
        std::vector<TetKeys> tets;
        for (size_t i = b; i < e; ++i) {
          tets.clear();
          AppendJ1aTetrahedra(tree, CellFromKey(leaves[i]), tets);
          for (const TetKeys& t : tets) {
            // Before, the pierced corners were outside: the tetrahedron was crossed where another
            // corner is inside, and is now where one stays outside.
            bool at_pierced = false, other_inside = false, outside = false;
            for (VertexKey k : t) {
              if (pierced.contains(k)) {
                at_pierced = true;
              } else if (values.find(k)->second.value < 0) {
                other_inside = true;
              } else {
                outside = true;
              }
            }
            if (at_pierced && outside && !other_inside) found[i].push_back(t);
          }
        }
      },
      &ctx));
  for (size_t i = 0; i < leaves.size(); ++i) {
    crossed_tets.insert(crossed_tets.end(), found[i].begin(), found[i].end());
    if (crossed_cells != nullptr) crossed_cells->resize(crossed_tets.size(), leaves[i]);
  }
  return absl::OkStatus();
}

// MarchingOptions::close_pierced_edges after the surface was followed: the pierced corners of the
// crossed tetrahedra are counted inside and the tetrahedra that this makes crossed are added.
absl::StatusOr<absl::flat_hash_map<VertexKey, Vec3d>> ClosePiercedEdges(
    const ImplicitFunction& field, const AdaptiveOctree& tree, const absl::flat_hash_set<uint64_t>& visited,
    const std::function<Vec3d(VertexKey)>& position, internal::CornerValues& corner_values,
    std::vector<TetKeys>& crossed_tets, std::vector<uint64_t>* crossed_cells, JobContext& ctx) {
  auto pierced = internal::PiercedCorners(
      field,
      [&](const internal::TetVisitor& visit) {
        for (const TetKeys& t : crossed_tets) visit(t, 0);
      },
      corner_values.values(), position, ctx);
  if (!pierced.ok() || pierced->empty()) return pierced;
  corner_values.CountInside(*pierced);
  LSQSURF_RETURN_IF_ERROR(
      AddTetrahedraCrossedAt(tree, visited, *pierced, corner_values.values(), crossed_tets, crossed_cells, ctx));
  return pierced;
}

// ExtractIsosurfaceOnTree with corner values known already (`corner_values`) and `stats` so far.
absl::StatusOr<IsosurfaceResult> TrackAndMarch(const ImplicitFunction& field, const AdaptiveOctree& tree,
                                               std::span<const OctreeCell> start, int64_t max_leaves,
                                               const MarchingOptions& marching, JobContext& ctx, const Box3* within,
                                               internal::CornerValues& corner_values, IsosurfaceStats stats) {
  auto inside = [&](const OctreeCell& c) {
    if (within == nullptr) return true;
    const double edge = tree.CellEdge(c.level);
    const Vec3d lo = tree.origin() + edge * Vec3d(c.x, c.y, c.z);
    return (lo.array() <= within->max().array()).all() && ((lo.array() + edge) >= within->min().array()).all();
  };
  // Follow the surface from leaf to leaf, a batch of leaves at a time: the tetrahedra and
  // neighbours of a leaf are found in parallel, only the shared vertex cache is filled serially.
  core::SubContext track_ctx(ctx, "tracking surface", 0.0, 0.75);
  const auto tracking_start = std::chrono::steady_clock::now();
  absl::flat_hash_set<uint64_t> visited;
  std::vector<OctreeCell> frontier;
  for (const OctreeCell& cell : start) {
    if (const OctreeCell* leaf = tree.LeafContaining(cell);
        leaf && inside(*leaf) && visited.insert(CellKey(*leaf)).second) {
      frontier.push_back(*leaf);
    }
  }
  // In key order: tracking numbers the vertices in the order it meets them, and callers gather
  // their starts in hash sets, whose order changes from table to table (absl salts it with the
  // table's address); the mesh's numbering, and what the order-dependent steps after marching
  // (relaxation, flips, hole loops) make of it, would change from run to run.
  std::sort(frontier.begin(), frontier.end(),
            [](const OctreeCell& a, const OctreeCell& b) { return CellKey(a) < CellKey(b); });
  // Bounds the memory of a batch (the tetrahedra of every leaf in it) on large first frontiers.
  constexpr size_t kLeavesPerBatch = 16384;
  std::vector<LeafWork> work(std::min(kLeavesPerBatch, frontier.size()));
  const auto& values = corner_values.values();
  const auto position = [&](internal::CornerKey k) { return tree.Position(k); };
  std::vector<TetKeys> crossed_tets;
  std::vector<uint64_t> crossed_cells;  // The leaf of each, when tracing.
  std::vector<OctreeCell> next;
  while (!frontier.empty()) {
    stats.cells_visited += static_cast<int64_t>(frontier.size());
    if (stats.cells_visited > max_leaves) {
      return absl::ResourceExhaustedError("the surface needs more than " + std::to_string(max_leaves) +
                                          " leaves; raise cell_size");
    }
    next.clear();
    for (size_t batch = 0; batch < frontier.size(); batch += kLeavesPerBatch) {
      const std::span<const OctreeCell> leaves =
          std::span<const OctreeCell>(frontier).subspan(batch, std::min(kLeavesPerBatch, frontier.size() - batch));
      if (work.size() < leaves.size()) work.resize(leaves.size());
      LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
          leaves.size(), 64,
          [&](size_t b, size_t e) {
            for (size_t i = b; i < e; ++i) {
              LeafWork& w = work[i];
              w.tets.clear();
              AppendJ1aTetrahedra(tree, leaves[i], w.tets);
              w.corners.clear();
              for (const TetKeys& t : w.tets) w.corners.insert(w.corners.end(), t.begin(), t.end());
              std::sort(w.corners.begin(), w.corners.end());
              w.corners.erase(std::unique(w.corners.begin(), w.corners.end()), w.corners.end());
            }
          },
          &ctx));
      for (size_t i = 0; i < leaves.size(); ++i) {
        stats.tetrahedra += static_cast<int64_t>(work[i].tets.size());
        for (VertexKey k : work[i].corners) {
          corner_values.Need(k);
        }
      }
      LSQSURF_RETURN_IF_ERROR(corner_values.Evaluate(field, position, stats, ctx));
      // Read-only on `values` and the tree, so the leaves are independent.
      LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
          leaves.size(), 64,
          [&](size_t b, size_t e) {
            for (size_t i = b; i < e; ++i) KeepCrossedTetrahedra(tree, values, leaves[i], work[i]);
          },
          &ctx));
      for (size_t i = 0; i < leaves.size(); ++i) {
        const LeafWork& w = work[i];
        if (w.tets.empty()) continue;
        ++stats.surface_cells;
        crossed_tets.insert(crossed_tets.end(), w.tets.begin(), w.tets.end());
        if (marching.trace) crossed_cells.resize(crossed_tets.size(), CellKey(leaves[i]));
        for (const OctreeCell& c : w.neighbors) {
          if (inside(c) && visited.insert(CellKey(c)).second) next.push_back(c);
        }
      }
    }
    std::swap(frontier, next);
    track_ctx.Report(
        std::min(0.95, static_cast<double>(stats.surface_cells) /
                           static_cast<double>(stats.surface_cells + static_cast<int64_t>(frontier.size()) + 1)));
  }
  work = {};
  absl::flat_hash_map<internal::CornerKey, Vec3d> pierced_corners;
  if (marching.close_pierced_edges) {
    auto pierced = ClosePiercedEdges(field, tree, visited, position, corner_values, crossed_tets,
                                     marching.trace ? &crossed_cells : nullptr, ctx);
    if (!pierced.ok()) return pierced.status();
    pierced_corners = *std::move(pierced);
    stats.pierced_corners = static_cast<int64_t>(pierced_corners.size());
  }
  visited = {};
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  stats.tracking_seconds = core::SecondsSince(tracking_start);

  core::SubContext emit_ctx(ctx, "extracting triangles", 0.75, 0.9);
  auto result = internal::MarchTetrahedra(
      field,
      [&](const internal::TetVisitor& visit) {
        for (size_t t = 0; t < crossed_tets.size(); ++t) visit(crossed_tets[t], marching.trace ? crossed_cells[t] : 0);
      },
      values, position, marching, stats, emit_ctx, &pierced_corners);
  if (!result.ok()) return result;
  corner_values = {};
  crossed_tets = {};
  crossed_cells = {};
  core::SubContext finish_ctx(ctx, "finishing the surface", 0.9, 1.0);
  LSQSURF_RETURN_IF_ERROR(internal::FinishSurface(field, marching, *result, finish_ctx));
  return result;
}

// Where the lattice edges of a leaf's tetrahedra (`tets`) cross the middle plane of one of the
// `probes` named in `held` with both ends on the other side of the probe's, within kNearLeaves of
// a leaf edge from it (its plane stands for a curved wall only that near): the crossing points,
// each with the side F should give it there, at most `limit` (one per probe).
constexpr double kNearLeaves = 0.75;
std::vector<SideProbe> MissedCrossings(const AdaptiveOctree& tree, const OctreeCell& leaf,
                                       std::span<const TetKeys> tets,
                                       const absl::flat_hash_map<VertexKey, FieldValue>& values,
                                       std::span<const SideProbe> probes, std::span<const uint32_t> held,
                                       size_t limit) {
  std::vector<SideProbe> missed;
  const double near = kNearLeaves * tree.CellEdge(leaf.level);
  for (uint32_t index : held) {
    const SideProbe& probe = probes[index];
    const Vec3d p = probe.point.cast<double>(), n = probe.normal.cast<double>();
    const auto wrong_side = [&](VertexKey k) {
      const double v = values.find(k)->second.value;
      return !std::isnan(v) && (v < 0) != probe.inside;
    };
    std::optional<Vec3d> crossing;
    for (const TetKeys& t : tets) {
      for (size_t a = 0; a < 4 && !crossing; ++a) {
        for (size_t c = a + 1; c < 4 && !crossing; ++c) {
          const Vec3d xa = tree.Position(t[a]), xc = tree.Position(t[c]);
          const double da = n.dot(xa - p), dc = n.dot(xc - p);
          if ((da < 0) == (dc < 0) || !wrong_side(t[a]) || !wrong_side(t[c])) continue;
          const Vec3d x = xa + (da / (da - dc)) * (xc - xa);
          if ((x - p).norm() <= near) crossing = x;
        }
      }
      if (crossing) break;
    }
    if (!crossing) continue;
    missed.push_back({crossing->cast<float>(), probe.normal, probe.inside});
    if (missed.size() == limit) break;
  }
  return missed;
}

// Splits, up to `levels` times, the leaves where the lattice misses a probe's side: an edge of
// their tetrahedra crosses the probe's middle plane near it with both ends on the other side (a
// wall thinner than the edge passes between them; MissedCrossings), and F where it crosses
// confirms the probe's side (beyond a plate's rim the plane goes on, the wall does not). The corners'
// values stay in `corner_values` for the extraction that follows.
struct ProbeSplits {
  int64_t leaves = 0;  // Split.
  int rounds = 0;      // That split any.
};
absl::StatusOr<ProbeSplits> SplitWhereProbesMissed(const ImplicitFunction& field, AdaptiveOctree& tree,
                                                   std::span<const SideProbe> probes, int levels,
                                                   internal::CornerValues& corner_values, IsosurfaceStats& stats,
                                                   JobContext& ctx) {
  const auto position = [&](internal::CornerKey k) { return tree.Position(k); };
  // One crossing confirmed per leaf is enough; a few candidates each keep the evaluations few.
  constexpr size_t kCandidatesPerLeaf = 6;
  ProbeSplits splits;
  for (int round = 0; round < levels; ++round) {
    absl::flat_hash_map<uint64_t, std::vector<uint32_t>> held;  // Probes by the leaf holding them.
    // A probe also speaks for the leaves beside its own along its plane, which its middle plane may
    // cut where they hold no probe of their own.
    for (uint32_t i = 0; i < probes.size(); ++i) {
      const OctreeCell* own = LeafHolding(tree, probes[i].point);
      if (own == nullptr) continue;
      const Vec3f u = probes[i].normal.unitOrthogonal(), v = probes[i].normal.cross(u);
      const float step = static_cast<float>(tree.CellEdge(own->level) / 2);
      std::array<uint64_t, 5> seen{};
      size_t count = 0;
      for (const Vec3f& offset :
           {Vec3f::Zero().eval(), (step * u).eval(), (-step * u).eval(), (step * v).eval(), (-step * v).eval()}) {
        const OctreeCell* leaf = LeafHolding(tree, probes[i].point + offset);
        if (leaf == nullptr || leaf->level >= tree.max_depth()) continue;
        const uint64_t key = CellKey(*leaf);
        if (std::find(seen.begin(), seen.begin() + static_cast<std::ptrdiff_t>(count), key) !=
            seen.begin() + static_cast<std::ptrdiff_t>(count)) {
          continue;
        }
        seen[count++] = key;
        held[key].push_back(i);
      }
    }
    std::vector<std::pair<uint64_t, std::vector<uint32_t>>> leaves(std::make_move_iterator(held.begin()),
                                                                   std::make_move_iterator(held.end()));
    held.clear();
    std::sort(leaves.begin(), leaves.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
    // Every corner of these leaves is evaluated: they hold the surface, so tracking needs them too.
    std::vector<std::vector<TetKeys>> tets(leaves.size());
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        leaves.size(), 64,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i) AppendJ1aTetrahedra(tree, CellFromKey(leaves[i].first), tets[i]);
        },
        &ctx));
    for (const auto& leaf_tets : tets) {
      for (const TetKeys& t : leaf_tets) {
        for (VertexKey k : t) corner_values.Need(k);
      }
    }
    LSQSURF_RETURN_IF_ERROR(corner_values.Evaluate(field, position, stats, ctx));
    const auto& values = corner_values.values();
    std::vector<std::vector<SideProbe>> leaf_candidates(leaves.size());
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        leaves.size(), 16,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i) {
            leaf_candidates[i] = MissedCrossings(tree, CellFromKey(leaves[i].first), tets[i], values, probes,
                                                 leaves[i].second, kCandidatesPerLeaf);
          }
        },
        &ctx));
    tets = {};
    std::vector<SideProbe> candidates;
    std::vector<size_t> candidate_leaf;
    for (size_t i = 0; i < leaves.size(); ++i) {
      candidates.insert(candidates.end(), leaf_candidates[i].begin(), leaf_candidates[i].end());
      candidate_leaf.resize(candidates.size(), i);
    }
    std::vector<Vec3d> at(candidates.size());
    std::vector<double> value(candidates.size());
    for (size_t k = 0; k < candidates.size(); ++k) at[k] = candidates[k].point.cast<double>();
    LSQSURF_RETURN_IF_ERROR(field.ValueOnlyBatch(at, value, &ctx));
    stats.field_evaluations += static_cast<int64_t>(candidates.size());
    int64_t split = 0;
    for (size_t k = 0; k < candidates.size(); ++k) {
      const OctreeCell leaf = CellFromKey(leaves[candidate_leaf[k]].first);
      if (std::isnan(value[k]) || (value[k] < 0) != candidates[k].inside || !tree.IsLeaf(leaf)) continue;
      tree.Split(leaf);
      ++split;
    }
    if (split == 0) break;
    splits.leaves += split;
    ++splits.rounds;
    tree.Balance();
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  }
  return splits;
}

}  // namespace

absl::StatusOr<IsosurfaceResult> ExtractIsosurfaceOnTree(const ImplicitFunction& field, const AdaptiveOctree& tree,
                                                         std::span<const OctreeCell> start, int64_t max_leaves,
                                                         const MarchingOptions& marching, JobContext& ctx,
                                                         const Box3* within) {
  LSQSURF_RETURN_IF_ERROR(Validate(marching));
  if (start.empty()) return absl::InvalidArgumentError("isosurface extraction needs start cells");
  internal::CornerValues corner_values;
  return TrackAndMarch(field, tree, start, max_leaves, marching, ctx, within, corner_values, {});
}

absl::StatusOr<IsosurfaceResult> ExtractIsosurfaceJ1a(const ImplicitFunction& field, std::span<const Vec3f> seeds,
                                                      const J1aIsosurfaceParams& params, JobContext& ctx) {
  if (!(params.cell_size > 0) || !std::isfinite(params.cell_size)) {
    return absl::InvalidArgumentError("cell_size must be a positive number");
  }
  LSQSURF_RETURN_IF_ERROR(Validate(params.marching));
  if (seeds.empty()) return absl::InvalidArgumentError("isosurface extraction needs seed points");
  if (params.probe_levels < 0 || params.probe_levels > kMaxProbeLevels) {
    return absl::InvalidArgumentError("probe_levels must be 0 to " + std::to_string(kMaxProbeLevels));
  }
  const int finer = params.probes.empty() ? 0 : params.probe_levels;
  core::SubContext build_ctx(ctx, "building the J1a tree", 0.0, 0.1);
  const Box3 box = core::BoundingBox(seeds);
  // Two finest cells of margin on every side, then the smallest power-of-two cube around it.
  const double extent = box.sizes().maxCoeff() + 4 * params.cell_size;
  const int depth = std::max(1, static_cast<int>(std::ceil(std::log2(extent / params.cell_size))));
  if (depth + finer > AdaptiveOctree::kMaxDepth) {
    return absl::InvalidArgumentError("cell_size is too small for the extent of the data");
  }
  const double side = params.cell_size * std::ldexp(1.0, depth);
  const Vec3d centre = box.center();
  AdaptiveOctree tree(Box3(centre - Vec3d::Constant(side / 2), centre + Vec3d::Constant(side / 2)), depth + finer);
  SurfaceBand band = MarkSurfaceBand(tree, seeds, depth);
  tree.Refine([&](const OctreeCell& c) { return band.ancestors.contains(CellKey(c)); });
  band.ancestors.clear();
  tree.Balance();
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  IsosurfaceStats stats;
  internal::CornerValues corner_values;
  MarchingOptions marching = params.marching;
  if (finer > 0) {
    auto split = SplitWhereProbesMissed(field, tree, params.probes, finer, corner_values, stats, build_ctx);
    if (!split.ok()) return split.status();
    stats.wall_splits = split->leaves;
    // The holes the filling closes are counted in edges: a slit as long has twice as many per level.
    marching.max_hole_edges <<= split->rounds;
  }
  build_ctx.Report(1.0);
  // The leaves holding seeds (split ones hold none: their children start instead).
  absl::flat_hash_set<uint64_t> start_keys;
  for (const Vec3f& seed : seeds) {
    if (const OctreeCell* leaf = LeafHolding(tree, seed)) start_keys.insert(CellKey(*leaf));
  }
  std::vector<OctreeCell> start;
  start.reserve(start_keys.size());
  for (uint64_t key : start_keys) start.push_back(CellFromKey(key));
  core::SubContext extract_ctx(ctx, "tracking surface", 0.1, 1.0);
  return TrackAndMarch(field, tree, start, params.max_leaves, marching, extract_ctx, nullptr, corner_values, stats);
}

absl::StatusOr<IsosurfaceResult> MarchLeaves(const ImplicitFunction& field, const AdaptiveOctree& tree,
                                             std::span<const OctreeCell> leaves, const MarchingOptions& marching,
                                             JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(Validate(marching));
  const auto tracking_start = std::chrono::steady_clock::now();
  IsosurfaceStats stats;
  std::vector<TetKeys> tets;
  std::vector<uint64_t> tet_cells;
  for (const OctreeCell& leaf : leaves) {
    AppendJ1aTetrahedra(tree, leaf, tets);
    tet_cells.resize(tets.size(), CellKey(leaf));
  }
  internal::CornerValues corner_values;
  for (const TetKeys& t : tets) {
    for (VertexKey k : t) corner_values.Need(k);
  }
  const auto position = [&](internal::CornerKey k) { return tree.Position(k); };
  LSQSURF_RETURN_IF_ERROR(corner_values.Evaluate(field, position, stats, ctx));
  const auto for_each_tet = [&](const internal::TetVisitor& visit) {
    for (size_t t = 0; t < tets.size(); ++t) visit(tets[t], tet_cells[t]);
  };
  absl::flat_hash_map<internal::CornerKey, Vec3d> pierced_corners;
  if (marching.close_pierced_edges) {
    auto pierced = internal::PiercedCorners(field, for_each_tet, corner_values.values(), position, ctx);
    if (!pierced.ok()) return pierced.status();
    pierced_corners = *std::move(pierced);
    corner_values.CountInside(pierced_corners);
    stats.pierced_corners = static_cast<int64_t>(pierced_corners.size());
  }
  stats.cells_visited = static_cast<int64_t>(leaves.size());
  stats.tracking_seconds = core::SecondsSince(tracking_start);
  MarchingOptions traced = marching;
  traced.trace = true;
  return internal::MarchTetrahedra(field, for_each_tet, corner_values.values(), position, traced, stats, ctx,
                                   &pierced_corners);
}

absl::Status FinishPatch(const ImplicitFunction& field, const MarchingOptions& marching, IsosurfaceResult& patch,
                         JobContext& ctx, std::span<const char> fixed) {
  return internal::FinishSurface(field, marching, patch, ctx, fixed);
}

}  // namespace lsqsurf::extract
