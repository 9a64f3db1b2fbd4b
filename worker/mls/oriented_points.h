// worker/mls/oriented_points.h — the indexed oriented cloud every MLS surface of this folder
// evaluates over: checked, with unit normals, in Morton order, with its kd-tree and spacing h.
#pragma once

#include <memory>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/kd_tree.h"

namespace lsqsurf::mls {

struct OrientedPoints {
  // Morton (Z-curve) order: neighbours in space are neighbours in memory, which keeps the
  // neighbour sums cache-friendly. The tree refers to `positions`, so the struct is moved, never
  // copied (moving a vector keeps its buffer).
  std::vector<core::Vec3f> positions;
  std::vector<core::Vec3f> normals;  // Unit length.
  std::unique_ptr<core::KdTree> tree;
  double spacing = 0;  // h: `spacing` as given, or spacing_scale × the mean nearest-neighbour distance.
};

// Checks and indexes `cloud` for the surface called `method` (named in the messages).
// Errors: kInvalidArgument (fewer than 4 points, no normals, a non-finite position or a zero or
// non-finite normal, all points coincident).
absl::StatusOr<OrientedPoints> IndexOrientedPoints(const core::PointCloud& cloud, double spacing, double spacing_scale,
                                                   std::string_view method);

}  // namespace lsqsurf::mls
