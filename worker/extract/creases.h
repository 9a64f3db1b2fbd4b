// worker/extract/creases.h — sharp creases and corners in extracted meshes (internal).
//
// Marching tetrahedra puts vertices on tetrahedron edges only, so where the surface folds (a
// machined edge, a corner, the intersection curve of a CSG result) each triangle across the fold
// cuts it off with a chord, at the scale of the tetrahedra. Here every mesh edge whose end normals
// differ by more than the crease angle is split where the two ends' tangent planes meet (the
// point of their common line nearest the edge's midpoint), provided that point lies on the
// surface (|F| small against the edge) and beside the edge. A triangle with two split edges then
// has the crease as an edge between them; one with three holds a corner, placed where the three
// tangent planes meet. Splits are keyed by the edge, so both triangles of an edge agree and a
// closed mesh stays closed.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "absl/status/status.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"

namespace lsqsurf::extract::internal {

struct CreaseCounts {
  int64_t crease_vertices = 0;   // Edge splits on creases.
  int64_t corners = 0;           // Vertices where three tangent planes meet.
  int64_t snapped_vertices = 0;  // Edge ends moved onto a crease that passes next to them.
};

// `mesh` must have unit normals (∇F) at its vertices; the new vertices get the mean of their
// edge's two. `crease_angle` in degrees, > 0. An edge with an end marked in `fixed` (empty, or
// one flag per vertex) is left as it is. `face_cells`, when given, holds a value per face, which
// the pieces of a split face inherit. Errors: kCancelled.
absl::Status SharpenCreases(const core::ImplicitFunction& field, double crease_angle, core::TriangleMesh& mesh,
                            CreaseCounts& counts, core::JobContext& ctx, std::span<const char> fixed = {},
                            std::vector<uint64_t>* face_cells = nullptr);

}  // namespace lsqsurf::extract::internal
