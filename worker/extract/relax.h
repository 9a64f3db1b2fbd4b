// worker/extract/relax.h — tangential relaxation of an extracted mesh on its implicit surface
// (internal).
//
// Marching leaves triangles of every shape: where the surface passes near a tetrahedron's
// corner or edge the triangles are thin. Each free vertex moves part of the way to the mean of
// its neighbours within its tangent plane; after the last step each moved vertex is projected
// back onto F = 0 by a Newton step along ∇F (unless its estimated drift, curvature × move² / 2,
// is below a thousandth of an edge), so the mesh stays on the surface while its triangles even
// out. Vertices on creases (split ones, and the ends of unsplit edges whose normals differ by
// more than about 25°) and on mesh borders stay where they are; a move that would turn the
// vertex's normal that much, or one of its triangles over, is not made (the vertex goes back
// where marching put it).
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"

namespace lsqsurf::extract::internal {

struct EnhanceCounts {
  int64_t relaxed_vertices = 0;  // Vertices left elsewhere than marching put them.
  int64_t flipped_edges = 0;
};

// `steps` steps of relaxation, edge flips where thin triangles are left (FlipPoorEdges), half as
// many steps again, and the projection of the moved vertices onto F = 0. `mesh` must have unit
// normals; vertices at or above `first_fixed` (crease vertices) stay. Errors: kCancelled.
absl::Status EnhanceTriangles(const core::ImplicitFunction& field, int steps, uint32_t first_fixed,
                              core::TriangleMesh& mesh, std::vector<uint64_t>* face_cells, EnhanceCounts& counts,
                              core::JobContext& ctx);

// Flips the longest edge of each triangle with an angle under 25° where the two faces across it
// are nearly coplanar and the flip makes the pair's smallest angle larger (the Delaunay idea,
// restricted to flat edges so that creases stay). With `face_cells`, only faces of one cell are
// flipped together, so every face still lies in the cell it is traced to. Vertices do not move.
absl::Status FlipPoorEdges(core::TriangleMesh& mesh, std::vector<uint64_t>* face_cells, int64_t& flips,
                           core::JobContext& ctx);

}  // namespace lsqsurf::extract::internal
