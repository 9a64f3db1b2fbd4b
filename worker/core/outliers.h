// worker/core/outliers.h — isolated points of a scan (a sensor's flying pixels, specks of dust,
// a stray return beyond the object), found by how far they lie from their neighbours compared
// with how far those neighbours lie from theirs.
//
// A point is isolated when the distance to its k-th nearest neighbour is more than `ratio` times
// the lower quartile of that distance over those neighbours (a stray among strays still has a few
// surface points beside it): a local test, so that a scan whose density
// falls with range (every depth camera's and lidar's) keeps its far, sparse parts, as a global
// mean-plus-sigma rule (PCL's StatisticalOutlierRemoval) would not. Points along a surface, however
// sparse, see neighbours as sparse as themselves; a point off it sees the surface's dense ones.
// Clusters of more than k isolated points together stay: they look like a surface.
#pragma once

#include <cstddef>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

struct IsolationParams {
  int neighbors = 8;   // k.
  double ratio = 3.0;  // How much farther than its neighbours' its k-th neighbour must be.
};

// Removes the isolated points of `cloud` (with their normals and attributes) and returns how many
// went. Errors: kCancelled.
absl::StatusOr<size_t> RemoveIsolatedPoints(PointCloud& cloud, const IsolationParams& params, JobContext& ctx);

}  // namespace lsqsurf::core
