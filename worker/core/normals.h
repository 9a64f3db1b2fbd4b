// worker/core/normals.h — normals for point clouds that arrive without them.
//
// Hoppe, DeRose, Duchamp, McDonald, Stuetzle, "Surface reconstruction from unorganized points",
// SIGGRAPH 1992: the normal of each point is the least-variance direction of its k nearest
// neighbours (PCA); signs are made consistent by walking a minimum spanning tree of the
// neighbourhood graph with edge cost 1 − |n_i · n_j|, so that orientation crosses flat regions
// first and sharp bends last. Each connected part is finally turned outward: the sign that
// makes Σ (p_i − centroid) · n_i positive, which is outward for closed, roughly star-shaped parts.
#pragma once

#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

struct NormalEstimationParams {
  int neighbors = 12;  // k for the PCA and for the orientation graph; 3..128.
};

absl::Status Validate(const NormalEstimationParams& params);

// Unit normals, one per point. Errors: kInvalidArgument (fewer than 3 points, bad params),
// kCancelled. Cost: one k-NN query per point plus an O(n k log(n k)) spanning tree.
absl::StatusOr<std::vector<Vec3f>> EstimateNormals(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                                   JobContext& ctx);

}  // namespace lsqsurf::core
