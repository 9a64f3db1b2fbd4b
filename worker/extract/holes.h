// worker/extract/holes.h — closing the small holes an extraction leaves (internal).
//
// An MLS field is trusted only where enough samples support it, and a surface whose samples thin
// out for a moment (the few samples on the rim of a wall thinner than the kernel) comes back with
// slits there: the field's zero lies just beyond the trusted band, so its triangles are dropped
// and the ones around them do not enclose them either. A hole of a few edges lies below the
// resolution the method has anyway, so it is closed with the triangles of least total area across
// its border, which put no vertex anywhere the border does not already reach.
#pragma once

#include <cstdint>
#include <functional>

#include "worker/core/geometry.h"

namespace lsqsurf::extract::internal {

// Closes every hole whose border is a loop of at most `max_edges` edges (3..kMaxHoleEdges) by the
// triangles of least total area across the loop, facing as the faces around it. No edge is made
// twice, so the mesh stays edge-manifold. A vertex where two fans of faces meet (two holes touch
// there, or one hole's border touches itself) is passed on the side of the gap each border edge
// faces, so it is manifold once its holes are closed. Left open: loops through a vertex where
// three fans meet or through an edge two faces run the same way, through a border vertex at the
// position of another one (welded, their borders may close each other), or with a vertex where
// `keep_open` says so. Faces are appended; vertices are not touched. Returns the holes closed.
// Where there is no hole: one pass over the faces.
inline constexpr int kMaxHoleEdges = 64;
int64_t FillSmallHoles(core::TriangleMesh& mesh, int max_edges,
                       const std::function<bool(const core::Vec3f&)>& keep_open = {});

}  // namespace lsqsurf::extract::internal
