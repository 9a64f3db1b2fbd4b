// worker/render/face_culling.h — when back faces may be skipped (internal to worker/render).
//
// On a closed, consistently oriented mesh seen from outside, every face turned away from the
// camera is hidden by one turned towards it, so the rasterizer may drop those faces without
// changing the picture; on llvmpipe that halves the cost of a large mesh. Open or inconsistent
// meshes keep every face (they are drawn two-sided).
#pragma once

#include <span>

#include "worker/core/geometry.h"

namespace lsqsurf::render {

enum class OutsideWinding {
  kUnknown,           // Open, inconsistently oriented, or orientation not clear: cull nothing.
  kCounterClockwise,  // Faces wind counter-clockwise seen from outside (the GL's default front).
  kClockwise,
};

// Closure: every directed edge (a, b) is matched by a (b, a), tested as equality of two
// multisets through sums of 64-bit hashes (a false "closed" has probability about 2^-64).
// Orientation: the sign of the enclosed volume; where there is one normal per vertex, 99 % of
// the faces must also agree with their normals on the same side. O(F), no allocation.
OutsideWinding ClosedMeshOutsideWinding(std::span<const core::Vec3f> vertices, std::span<const core::Vec3f> normals,
                                        std::span<const core::Triangle> faces);

}  // namespace lsqsurf::render
