#include "worker/core/geometry.h"

#include <cmath>

namespace lsqsurf::core {

Box3 BoundingBox(std::span<const Vec3f> points) {
  Box3 box;  // Default-constructed AlignedBox is empty.
  for (const Vec3f& p : points) box.extend(p.cast<double>());
  return box;
}

double Diagonal(const Box3& box) { return box.isEmpty() ? 0.0 : box.diagonal().norm(); }

int64_t FindNonFinite(std::span<const Vec3f> points) {
  for (size_t i = 0; i < points.size(); ++i) {
    if (!points[i].allFinite()) return static_cast<int64_t>(i);
  }
  return -1;
}

}  // namespace lsqsurf::core
