#include "worker/jobs/shared_extraction.h"

#include <vector>

#include "worker/extract/j1a_isosurface.h"
#include "worker/extract/thin_walls.h"
#include "worker/jobs/job_kind.h"

namespace lsqsurf::jobs {

absl::StatusOr<extract::IsosurfaceResult> ExtractShared(const core::ImplicitFunction& field,
                                                        const core::PointCloud& cloud, const ExtractionHints& hints,
                                                        core::JobContext& ctx) {
  extract::MarchingOptions marching;
  marching.refine_steps = hints.refine_steps;
  marching.max_hole_edges = kClosedHoleEdges;
  if (hints.extractor == SurfaceExtractor::kJ1a) {
    extract::J1aIsosurfaceParams j1a;
    j1a.cell_size = 2 * hints.vertex_spacing;
    j1a.max_leaves = LeavesWithin(hints.memory_bytes, j1a.max_leaves);
    j1a.marching = marching;
    std::vector<extract::SideProbe> probes;
    if (hints.wall_levels > 0 && cloud.normals.size() == cloud.positions.size()) {
      extract::ThinWallParams walls;
      if (hints.noisy_walls) walls.max_spread = extract::kNoisyWallSpread;
      auto found = extract::ThinWallProbes(cloud.positions, cloud.normals, j1a.cell_size, walls, ctx);
      if (!found.ok()) return found.status();
      probes = *std::move(found);
      j1a.probes = probes;
      j1a.probe_levels = hints.wall_levels;
    }
    return extract::ExtractIsosurfaceJ1a(field, cloud.positions, j1a, ctx);
  }
  // A grid cube holds about what a J1a leaf does (its corners, tetrahedra and crossings).
  return extract::ExtractIsosurface(
      field, cloud.positions,
      {hints.vertex_spacing, LeavesWithin(hints.memory_bytes, extract::IsosurfaceParams{}.max_cells), marching}, ctx);
}

}  // namespace lsqsurf::jobs
