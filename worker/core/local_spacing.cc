#include "worker/core/local_spacing.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "worker/core/parallel.h"

namespace lsqsurf::core {

LocalSpacing::LocalSpacing(const KdTree& tree, const JobContext* ctx) : tree_(tree), nearest_(tree.size(), 0.0f) {
  // Errors are cancellation only, which the caller reads from ctx.
  (void)ParallelFor(
      tree.size(), 4096,
      [&](size_t begin, size_t end) {
        std::vector<Neighbor> found;
        for (size_t i = begin; i < end; ++i) {
          tree_.Knn(tree_.points()[i], 2, found);
          nearest_[i] = found.size() > 1 ? std::sqrt(found[1].distance2) : 0.0f;
        }
      },
      ctx);
}

LocalSpacing::Reading LocalSpacing::At(const Vec3f& query, std::vector<Neighbor>& scratch) const {
  Reading r;
  tree_.Knn(query, kAround, scratch);
  if (scratch.empty()) return r;
  std::array<float, kAround> spacings{};
  const size_t n = std::min(scratch.size(), kAround);
  for (size_t i = 0; i < n; ++i) spacings[i] = nearest_[scratch[i].index];
  std::nth_element(spacings.begin(), spacings.begin() + n / 2, spacings.begin() + n);
  r.nearest = std::sqrt(static_cast<double>(scratch[0].distance2));
  r.spacing = spacings[n / 2];
  return r;
}

double LocalSpacing::MedianNearest() const {
  if (nearest_.size() < 2) return 0;
  std::vector<float> sorted = nearest_;
  std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
  return sorted[sorted.size() / 2];
}

}  // namespace lsqsurf::core
