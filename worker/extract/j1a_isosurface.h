// worker/extract/j1a_isosurface.h — zero-set extraction on the adaptive J1a tetrahedralization.
//
// The seeds' cubes at the finest level, and their 26 neighbours, are refined to the finest
// level; the tree is 2:1 balanced and triangulated with J1a (see j1a.h). Extraction follows the
// surface from leaf to leaf, starting at the leaves that hold seeds: F is evaluated once per
// J1a vertex (cached by key), and marching tetrahedra run on the leaves the surface crosses.
// Tetrahedra have no ambiguous cases and the triangulation is conforming, so the result is
// crack-free and edge-manifold; it is closed wherever F is defined.
#pragma once

#include <cstdint>
#include <functional>
#include <span>

#include "absl/container/flat_hash_set.h"
#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/extract/isosurface.h"
#include "worker/extract/j1a.h"

namespace lsqsurf::extract {

// A point known to lie inside the surface (the middle of a wall) or outside it (of a gap), and the
// normal of the wall's or gap's middle plane there.
struct SideProbe {
  Vec3f point = Vec3f::Zero();
  Vec3f normal = Vec3f::UnitZ();
  bool inside = true;
};

struct J1aIsosurfaceParams {
  double cell_size = 0.0;           // Edge of the finest leaves, model units; must be > 0.
  int64_t max_leaves = 20'000'000;  // Visited leaves before failing with kResourceExhausted.
  MarchingOptions marching;
  // Points that must come out on their side of the surface (thin walls and gaps, thin_walls.h):
  // a leaf is split, up to `probe_levels` times, where an edge of its tetrahedra crosses a nearby
  // probe's middle plane with F putting both ends on the other side (the wall passes between
  // them), and F where it crosses confirms the probe's side.
  std::span<const SideProbe> probes;
  int probe_levels = 0;  // 0..kMaxProbeLevels.
};
inline constexpr int kMaxProbeLevels = 3;

// Errors: kInvalidArgument (bad params, no seeds, more than 2^19 finest cells per axis),
// kResourceExhausted, kCancelled. `cells_visited` counts leaves, `surface_cells` surface leaves,
// `wall_splits` the leaves split for the probes.
absl::StatusOr<IsosurfaceResult> ExtractIsosurfaceJ1a(const ImplicitFunction& field, std::span<const Vec3f> seeds,
                                                      const J1aIsosurfaceParams& params, JobContext& ctx);

// The band of `level` cells that hold a point or touch one that does: `occupied` holds the keys
// of the cells with points, `ancestors` every proper ancestor of a band cell (the cells to split
// so that the band exists as leaves).
struct SurfaceBand {
  absl::flat_hash_set<uint64_t> occupied;
  absl::flat_hash_set<uint64_t> ancestors;
};
SurfaceBand MarkSurfaceBand(const AdaptiveOctree& tree, std::span<const Vec3f> points, int level);

// How far the flat triangles cut from cells of edge `edge` near `centre` would stray from {F = 0}:
// κ ℓ² / 8 for chords of length ℓ (the J1a triangles' typical edge) over a surface of curvature κ,
// κ measured as the turn of ∇F between points half an edge apart on either side of the surface
// point nearest `centre` (5 gradient evaluations). Infinite where ∇F vanishes or is not finite.
double EstimateChordError(const ImplicitFunction& field, const Vec3d& centre, double edge);

// Splits every ancestor of the `coarse` band's cells, then, from the coarse band's level down,
// the cells of `fine.ancestors` for which `wants_finer(cell)` holds (the cells of one level are
// decided in parallel). The tree is not balanced yet. Errors: kCancelled.
absl::Status RefineSurfaceBand(AdaptiveOctree& tree, const SurfaceBand& coarse, int coarse_level,
                               const SurfaceBand& fine, const std::function<bool(const OctreeCell&)>& wants_finer,
                               JobContext& ctx);

// Extraction on a caller-built, 2:1-balanced tree: follows the surface from the `start` leaves
// across every leaf that touches a crossed one (with `within`, only leaves whose cube meets it).
// Errors: kInvalidArgument (no start leaves), kResourceExhausted (more than `max_leaves` visited),
// kCancelled.
absl::StatusOr<IsosurfaceResult> ExtractIsosurfaceOnTree(const ImplicitFunction& field, const AdaptiveOctree& tree,
                                                         std::span<const OctreeCell> start, int64_t max_leaves,
                                                         const MarchingOptions& marching, JobContext& ctx,
                                                         const Box3* within = nullptr);

// Marching tetrahedra on every tetrahedron of `leaves` (leaves of a balanced tree), traced (each
// face names its leaf by CellKey), not finished: no creases, no relaxation (PatchJoin comes first).
// Errors: kCancelled.
absl::StatusOr<IsosurfaceResult> MarchLeaves(const ImplicitFunction& field, const AdaptiveOctree& tree,
                                             std::span<const OctreeCell> leaves, const MarchingOptions& marching,
                                             JobContext& ctx);

// Creases and relaxation for a patch from MarchLeaves once PatchJoin has marked its seam: the
// vertices flagged in `fixed` (one per patch vertex) neither move nor end a split edge, so the
// patch still meets the kept mesh exactly. Errors: kCancelled.
absl::Status FinishPatch(const ImplicitFunction& field, const MarchingOptions& marching, IsosurfaceResult& patch,
                         JobContext& ctx, std::span<const char> fixed);

}  // namespace lsqsurf::extract
