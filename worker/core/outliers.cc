#include "worker/core/outliers.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::core {

absl::StatusOr<size_t> RemoveIsolatedPoints(PointCloud& cloud, const IsolationParams& params, JobContext& ctx) {
  const size_t n = cloud.size(), k = static_cast<size_t>(params.neighbors);
  if (n <= 2 * k) return 0;
  const KdTree tree(cloud.positions);
  std::vector<float> reach(n);  // Squared distance to the k-th neighbour (the point itself is the 0th).
  std::vector<uint32_t> neighbours(n * k);
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        std::vector<Neighbor> nn;
        for (size_t i = begin; i < end; ++i) {
          tree.Knn(cloud.positions[i], k + 1, nn);
          reach[i] = nn.back().distance2;
          for (size_t j = 0; j < k; ++j) neighbours[i * k + j] = nn[std::min(j + 1, nn.size() - 1)].index;
        }
      },
      &ctx));
  const float ratio2 = static_cast<float>(params.ratio * params.ratio);
  std::vector<uint8_t> isolated(n, 0);
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        std::vector<float> theirs(k);
        for (size_t i = begin; i < end; ++i) {
          for (size_t j = 0; j < k; ++j) theirs[j] = reach[neighbours[i * k + j]];
          // The lower quartile: a stray among strays still has a few surface points beside it.
          std::nth_element(theirs.begin(), theirs.begin() + static_cast<ptrdiff_t>(k / 4), theirs.end());
          isolated[i] = reach[i] > ratio2 * theirs[k / 4];
        }
      },
      &ctx));
  const auto removed = static_cast<size_t>(std::count(isolated.begin(), isolated.end(), 1));
  if (removed > 0) RemovePoints(cloud, isolated);
  return removed;
}

}  // namespace lsqsurf::core
