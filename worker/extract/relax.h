// worker/extract/relax.h — tangential relaxation of an extracted mesh on its implicit surface
// (internal).
//
// Marching leaves triangles of every shape: where the surface passes near a tetrahedron's
// corner or edge the triangles are thin. Each free vertex moves part of the way to the mean of
// its neighbours within its tangent plane and is then projected back onto F = 0 by Newton steps
// along ∇F, so the mesh stays on the surface while its triangles even out. Vertices on creases
// (split ones, and the ends of unsplit edges whose normals differ by more than about 25°) and on
// mesh borders stay where they are; a move that would turn the vertex's normal that much, or one
// of its triangles over, is not made.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"

namespace lsqsurf::extract::internal {

// `mesh` must have unit normals; vertices at or above `first_fixed` (crease vertices) stay.
// Returns the number of vertex moves made. Errors: kCancelled.
absl::Status RelaxTangentially(const core::ImplicitFunction& field, int steps, uint32_t first_fixed,
                               core::TriangleMesh& mesh, int64_t& moves, core::JobContext& ctx);

// Flips the longest edge of each triangle with an angle under 25° where the two faces across it
// are nearly coplanar and the flip makes the pair's smallest angle larger (the Delaunay idea,
// restricted to flat edges so that creases stay). With `face_cells`, only faces of one cell are
// flipped together, so every face still lies in the cell it is traced to. Vertices do not move.
absl::Status FlipPoorEdges(core::TriangleMesh& mesh, std::vector<uint64_t>* face_cells, int64_t& flips,
                           core::JobContext& ctx);

}  // namespace lsqsurf::extract::internal
