// worker/extract/marching_tets.h — marching tetrahedra shared by the extractors (internal).
//
// Input: tetrahedra named by the keys of their corners, the field value at every corner, and
// the position of a key. Crossings are keyed by the unordered corner pair, so neighbouring
// tetrahedra share output vertices; each root is refined on F along its edge (regula falsi,
// core::RefineRootOnSegment); triangles are oriented from F < 0 to F >= 0 using the corner positions. Roots where F
// is not `defined` make their triangles untrusted: those are dropped unless they form a small
// edge-connected patch (a pinhole) inside trusted surface; conversely, small clusters of trusted
// triangles that the dropped ones cut off from the rest (specks) are dropped too.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::extract::internal {

using CornerKey = uint64_t;
using TetCorners = std::array<CornerKey, 4>;

// An undirected mesh edge as one key: the smaller vertex index in the high half.
inline uint64_t EdgeKey(uint32_t a, uint32_t b) { return (uint64_t{std::min(a, b)} << 32) | std::max(a, b); }

// Field values at lattice corners, filled in batches as a surface search discovers them (one
// batched field call per batch: the engines evaluate batches in parallel).
class CornerValues {
 public:
  // Queues the corner unless its value is known or already queued.
  void Need(CornerKey key) {
    if (values_.try_emplace(key).second) pending_.push_back(key);
  }
  // Evaluates the queued corners; counts them in `stats.field_evaluations`. Errors: kCancelled.
  absl::Status Evaluate(const ImplicitFunction& field, const std::function<Vec3d(CornerKey)>& position,
                        IsosurfaceStats& stats, JobContext& ctx);
  const absl::flat_hash_map<CornerKey, FieldValue>& values() const { return values_; }
  // Counts evaluated corners inside whatever F says there (PiercedCorners).
  void CountInside(const absl::flat_hash_map<CornerKey, Vec3d>& corners);

 private:
  absl::flat_hash_map<CornerKey, FieldValue> values_;
  std::vector<CornerKey> pending_;
  std::vector<Vec3d> pending_positions_;
  std::vector<double> pending_values_;
};

// `for_each_tet(visit)` must call `visit(tet, cell)` for every tetrahedron to examine, `cell`
// naming where it lies (what the trace records per face); every corner must be in `values`. Tetrahedra with a NaN
// corner or no sign change produce nothing. The result's statistics are `tracking` (what the caller's surface search
// counted) plus `crossings`, `rejected_polygons` and `restored_triangles`. Creases and relaxation are FinishSurface's,
// so that callers free their search structures first. `pierced` (PiercedCorners, counted inside
// in `values`) are each their own crossing, moved onto the surface. Errors: kCancelled.
using TetVisitor = std::function<void(const TetCorners&, uint64_t cell)>;
absl::StatusOr<IsosurfaceResult> MarchTetrahedra(const ImplicitFunction& field,
                                                 const std::function<void(const TetVisitor&)>& for_each_tet,
                                                 const absl::flat_hash_map<CornerKey, FieldValue>& values,
                                                 const std::function<Vec3d(CornerKey)>& position,
                                                 const MarchingOptions& params, const IsosurfaceStats& tracking,
                                                 JobContext& ctx,
                                                 const absl::flat_hash_map<CornerKey, Vec3d>* pierced = nullptr);

// Splits edges on creases and relaxes the marched mesh as `params` ask; drops the vertex normals
// unless they are wanted. Vertices marked in `fixed` (when given, one flag per vertex) neither
// move nor end a split edge: the border where a patch joins a kept mesh. Errors: kCancelled.
absl::Status FinishSurface(const ImplicitFunction& field, const MarchingOptions& params, IsosurfaceResult& result,
                           JobContext& ctx, std::span<const char> fixed = {});

// The ends of the lattice edges that a part thinner than the edge passes through: both ends lie
// just outside (F, about a distance there, under kPiercedShare of the edge's length) while F is
// negative at the edge's midpoint, as where a pointed corner's tip passes between corners on its
// opposite faces. Marching cuts the part along such an edge and leaves a tunnel through it (a
// handle). Counted inside, with their crossings where Newton steps take them onto the surface,
// the ends close it. An edge whose ends do not reach the surface within kPiercedReach of its
// length (beside an acute ridge F is much less than the distance) is left alone. Looks at the edges
// of the tetrahedra `for_each_tet` visits; returns each corner with its place on the surface.
// Errors: kCancelled.
inline constexpr double kPiercedShare = 0.05, kPiercedReach = 0.1;
absl::StatusOr<absl::flat_hash_map<CornerKey, Vec3d>> PiercedCorners(
    const ImplicitFunction& field, const std::function<void(const TetVisitor&)>& for_each_tet,
    const absl::flat_hash_map<CornerKey, FieldValue>& values, const std::function<Vec3d(CornerKey)>& position,
    JobContext& ctx);

// The trace's name of the lattice edge between two corners (order-free, never 0).
uint64_t LatticeEdgeHash(CornerKey a, CornerKey b);

}  // namespace lsqsurf::extract::internal
