// worker/jobs/shared_extraction.h — where the surface methods without an extractor of their own
// (iaMLS and the other MLS surfaces) hand their function: the one shared extractor, on J1a leaves
// of twice the vertex spacing (a leaf has vertices at half its edge), with the wall probes of
// extract/thin_walls.h, or on a uniform grid of the vertex spacing.
#pragma once

#include <cstdint>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/extract/isosurface.h"
#include "worker/jobs/surface_params.h"

namespace lsqsurf::jobs {

// The wall probes' splits where a method's `wall_levels` is chosen (-1) and the cloud is clean: a
// plate a third of a leaf thick needs two (its leaves' tetrahedra are then thinner than it).
inline constexpr int kChosenWallLevels = 2;

// Holes whose border has up to 32 edges (about ten cells around: a few kernel widths across) are
// slits where the field's trust ended just short of its zero, or where a wall thinner than the
// cells opened; an open scan's border is far longer. The shared extractor and whole PU surfaces
// close them (extract::MarchingOptions::max_hole_edges).
inline constexpr int kClosedHoleEdges = 32;

struct ExtractionHints {
  double vertex_spacing = 0;  // Model units.
  int refine_steps = 3;
  int wall_levels = 0;       // extract::J1aIsosurfaceParams::probe_levels, with thin_walls.h's probes.
  bool noisy_walls = false;  // The probes take extract::kNoisyWallSpread (a cloud mostly of noisy walls).
  SurfaceExtractor extractor = SurfaceExtractor::kJ1a;
  int64_t memory_bytes = 0;  // The job's memory limit (RunEnvironment::memory_bytes).
};

// Holes of up to kClosedHoleEdges border edges are closed. Errors: those of the extractor.
absl::StatusOr<extract::IsosurfaceResult> ExtractShared(const core::ImplicitFunction& field,
                                                        const core::PointCloud& cloud, const ExtractionHints& hints,
                                                        core::JobContext& ctx);

}  // namespace lsqsurf::jobs
