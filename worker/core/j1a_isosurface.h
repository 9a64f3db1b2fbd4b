// worker/core/j1a_isosurface.h — zero-set extraction on the adaptive J1a tetrahedralization.
//
// The seeds' cubes at the finest level, and their 26 neighbours, are refined to the finest
// level; the tree is 2:1 balanced and triangulated with J1a (see j1a.h). Extraction follows the
// surface from leaf to leaf, starting at the leaves that hold seeds: F is evaluated once per
// J1a vertex (cached by key), and marching tetrahedra run on the leaves the surface crosses.
// Tetrahedra have no ambiguous cases and the triangulation is conforming, so the result is
// crack-free and edge-manifold; it is closed wherever F is defined.
#pragma once

#include <cstdint>
#include <span>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/isosurface.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

struct J1aIsosurfaceParams {
  double cell_size = 0.0;          // Edge of the finest leaves, model units; must be > 0.
  int64_t max_leaves = 20'000'000; // Visited leaves before failing with kResourceExhausted.
  MarchingOptions marching;
};

// Errors: kInvalidArgument (bad params, no seeds, more than 2^19 finest cells per axis),
// kResourceExhausted, kCancelled. `cells_visited` counts leaves, `surface_cells` surface leaves.
absl::StatusOr<IsosurfaceResult> ExtractIsosurfaceJ1a(const ImplicitFunction& field,
                                                      std::span<const Vec3f> seeds,
                                                      const J1aIsosurfaceParams& params,
                                                      JobContext& ctx);

}  // namespace lsqsurf::core
