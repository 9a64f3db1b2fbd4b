#include "worker/extract/thin_walls.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <optional>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::extract {

namespace {

constexpr float kFacingCosine = static_cast<float>(kWallFacingCosine);
// Enough of the other sheet to trust the median: a wall 0.8 of the radius thick leaves a quarter
// of the ball's points on its far side; a stray flipped normal or two on one sheet do not count.
constexpr size_t kMinFacing = 3;
constexpr double kMinFacingShare = 0.1;
// A wall of a few dozen points holds one of every this many.
constexpr size_t kSampleStride = 16;

}  // namespace

absl::StatusOr<std::vector<SideProbe>> ThinWallProbes(std::span<const core::Vec3f> points,
                                                      std::span<const core::Vec3f> normals, double leaf_edge,
                                                      const ThinWallParams& params, core::JobContext& ctx) {
  if (normals.size() != points.size()) return absl::InvalidArgumentError("thin walls need one normal per point");
  if (!(leaf_edge > 0) || !std::isfinite(leaf_edge)) {
    return absl::InvalidArgumentError("the leaf edge must be a positive number");
  }
  if (points.empty()) return std::vector<SideProbe>{};
  const core::KdTree tree(points);
  const float reach = static_cast<float>(params.max_leaf_share * leaf_edge);
  const double thinnest = params.min_leaf_share * leaf_edge;
  const auto probe_at = [&](size_t i, std::vector<core::Neighbor>& near,
                            std::vector<float>& offsets) -> std::optional<SideProbe> {
    const core::Vec3f& n = normals[i];
    tree.Radius(points[i], reach, near);
    offsets.clear();  // Along the normal: negative behind the point (a wall).
    for (const core::Neighbor& m : near) {
      if (n.dot(normals[m.index]) < kFacingCosine) offsets.push_back(n.dot(points[m.index] - points[i]));
    }
    if (offsets.size() < kMinFacing ||
        static_cast<double>(offsets.size()) < kMinFacingShare * static_cast<double>(near.size())) {
      return std::nullopt;
    }
    const auto at = [&](size_t share_of_4) {
      const auto it = offsets.begin() + static_cast<std::ptrdiff_t>(offsets.size() * share_of_4 / 4);
      std::nth_element(offsets.begin(), it, offsets.end());
      return *it;
    };
    const float far = at(2), spread = at(3) - at(1);
    offsets.clear();  // The point's own sheet, whose median offset is the point's noise.
    for (const core::Neighbor& m : near) {
      if (n.dot(normals[m.index]) > -kFacingCosine) offsets.push_back(n.dot(points[m.index] - points[i]));
    }
    const float own = at(2), offset = far - own;
    if (!(std::abs(offset) >= thinnest) || spread > params.max_spread * std::abs(offset)) return std::nullopt;
    return SideProbe{points[i] + (own + offset / 2) * n, n, offset < 0};
  };
  // Every kSampleStride-th point first: a cloud without walls (most scans) pays for those only.
  std::atomic<bool> any = false;
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor((points.size() + kSampleStride - 1) / kSampleStride, 64,
                                            [&](size_t begin, size_t end) {
                                              std::vector<core::Neighbor> near;
                                              std::vector<float> offsets;
                                              for (size_t k = begin; k < end && !any.load(std::memory_order_relaxed);
                                                   ++k) {
                                                if (probe_at(k * kSampleStride, near, offsets)) any = true;
                                              }
                                            },
                                            &ctx));
  if (!any) return std::vector<SideProbe>{};
  std::vector<std::optional<SideProbe>> found(points.size());
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      points.size(), 256,
      [&](size_t begin, size_t end) {
        std::vector<core::Neighbor> near;
        std::vector<float> offsets;
        for (size_t i = begin; i < end; ++i) found[i] = probe_at(i, near, offsets);
      },
      &ctx));
  std::vector<SideProbe> probes;
  for (const auto& probe : found) {
    if (probe) probes.push_back(*probe);
  }
  return probes;
}

}  // namespace lsqsurf::extract
