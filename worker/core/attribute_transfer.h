// worker/core/attribute_transfer.h — a cloud's per-point attributes (colour, intensity, ...)
// carried to the vertices of the surface made from it.
//
// Each vertex takes the Gaussian-weighted mean of its 4 nearest points' values, the width set
// by those points' own distances (σ = half the 4th distance), so that the mesh's colour follows
// the scan's at the scan's own resolution. The weights are these, not the surface method's
// (PU's partition of unity, an MLS kernel): a vertex lies within a spacing of the points that
// made it, where the two differ little.
#pragma once

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

// The names the mesh keeps from `cloud` when the user names none: red, green and blue (when all
// three are there) and intensity (when there).
std::vector<std::string> DefaultCarriedAttributes(const PointCloud& cloud);

// Appends to `mesh` one vertex attribute per name in `names`, interpolated from `cloud`'s.
// Errors: kInvalidArgument naming an attribute the cloud lacks (and those it has), kCancelled.
absl::Status CarryAttributes(const PointCloud& cloud, const std::vector<std::string>& names, TriangleMesh& mesh,
                             JobContext& ctx);

}  // namespace lsqsurf::core
