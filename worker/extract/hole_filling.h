// worker/extract/hole_filling.h — closing every hole of an open surface, on request.
//
// A surface method leaves the surface open where the data do not reach (the bottom no scan saw,
// the gap between two stations); a user who wants a closed model asks for it to be closed there.
// Each hole is closed as Liepa (2003) proposes: its border loop is triangulated (long loops first
// cut in two by their shortest chord, recursively, the pieces by the triangles of least area, thin
// ones penalised), the triangles refined until their edges are about as long as the surface's
// around the border, the edges flipped towards Delaunay, the new vertices relaxed to their
// neighbours' centroids (even triangles), then placed by a thin-plate fairing with cotangent
// weights (the bi-Laplacian of the positions zero, with the border and the faces around it
// fixed), so that the filling meets the surface around it smoothly and bulges as it does. The
// new vertices are appended to the mesh.
#pragma once

#include <cstdint>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::extract {

struct HoleFillingParams {
  // Holes whose border has more edges stay open (0: no limit).
  int64_t max_border_edges = 0;
  // Edges of the filling at most this many times the median edge of the faces around its border.
  double edge_scale = 1.4;
  // Thin-plate fairing (bi-Laplacian: the filling's tangent plane meets the surface's at the
  // border); false: a membrane (Laplacian: the least area the border spans, creased there).
  bool thin_plate = true;
};

struct HoleFillingStats {
  int64_t holes_filled = 0;
  int64_t holes_left = 0;  // Too long, through a non-manifold vertex, or not triangulable.
  int64_t vertices_added = 0;
  int64_t faces_added = 0;
  // Holes whose thin plate failed with both weights (a singular system, or positions far off): their
  // vertices stay where the relaxation put them.
  int64_t unfaired = 0;
  // Holes whose thin plate failed with cotangent weights and was solved with umbrella weights,
  // which sag (about half a smooth bulge): where the filled surface is flatter than its border.
  int64_t umbrella_faired = 0;
};

// Closes the holes of `mesh` as above. The new vertices come after the old ones; normals (where
// the mesh has them) are the new faces' for them, and each vertex attribute takes its border's
// mean. Errors: kCancelled.
absl::StatusOr<HoleFillingStats> FillHoles(core::TriangleMesh& mesh, const HoleFillingParams& params,
                                           core::JobContext& ctx);

}  // namespace lsqsurf::extract
