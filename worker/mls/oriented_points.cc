#include "worker/mls/oriented_points.h"

#include <cmath>

#include "worker/core/strings.h"

namespace lsqsurf::mls {

absl::StatusOr<OrientedPoints> IndexOrientedPoints(const core::PointCloud& cloud, double spacing, double spacing_scale,
                                                   std::string_view method) {
  if (cloud.size() < 4) return absl::InvalidArgumentError(core::StrCat(method, " needs at least 4 points"));
  if (!cloud.has_normals()) {
    return absl::InvalidArgumentError(core::StrCat(method, " needs oriented normals (estimate them first)"));
  }
  if (const int64_t bad = core::FindNonFinite(cloud.positions); bad >= 0) {
    return absl::InvalidArgumentError(core::StrCat("point ", bad, " has a non-finite position"));
  }
  for (size_t i = 0; i < cloud.size(); ++i) {
    const float length = cloud.normals[i].norm();
    if (!(length > 0) || !std::isfinite(length)) {
      return absl::InvalidArgumentError(core::StrCat("normal ", i, " is zero or not finite"));
    }
  }
  OrientedPoints out;
  const std::vector<uint32_t> order = core::MortonOrder(cloud.positions);
  out.positions.resize(cloud.size());
  out.normals.resize(cloud.size());
  for (size_t i = 0; i < order.size(); ++i) {
    out.positions[i] = cloud.positions[order[i]];
    out.normals[i] = cloud.normals[order[i]].normalized();
  }
  out.tree = std::make_unique<core::KdTree>(out.positions);
  out.spacing = spacing > 0 ? spacing : spacing_scale * core::MeanNearestNeighborDistance(*out.tree);
  if (!(out.spacing > 0)) {
    return absl::InvalidArgumentError("all points coincide: there is no spacing to size the kernel by");
  }
  return out;
}

}  // namespace lsqsurf::mls
