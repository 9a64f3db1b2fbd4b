#include "worker/volume/box_grid.h"

#include <algorithm>
#include <cmath>

namespace lsqsurf::volume {

BoxGrid::BoxGrid(const core::Box3& bounds, const core::Vec3d& bin_size, double max_bins, size_t count,
                 const std::function<core::Box3(size_t)>& box) {
  const core::Vec3d size = bounds.sizes().cwiseMax(1e-30);
  double total = 1;
  for (int a = 0; a < 3; ++a) total *= std::ceil(size[a] / bin_size[a] + 1e-9);
  const double grow = total > max_bins ? std::cbrt(total / max_bins) : 1.0;
  origin_ = bounds.min();
  for (int a = 0; a < 3; ++a) {
    bins_[a] = std::max(1, static_cast<int>(std::ceil(size[a] / (bin_size[a] * grow) + 1e-9)));
    inv_bin_[a] = bins_[a] / size[a];
  }
  const size_t bin_count = static_cast<size_t>(bins_[0]) * bins_[1] * bins_[2];
  start_.assign(bin_count + 1, 0);
  // Two passes (count, fill) keep the bins in one array.
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<uint32_t> cursor;
    if (pass == 1) {
      for (size_t b = 0; b < bin_count; ++b) start_[b + 1] += start_[b];
      items_.resize(start_[bin_count]);
      cursor.assign(start_.begin(), start_.end() - 1);
    }
    for (size_t i = 0; i < count; ++i) {
      const core::Box3 b = box(i);
      std::array<int, 3> lo, hi;
      for (int a = 0; a < 3; ++a) {
        lo[a] = std::clamp(static_cast<int>((b.min()[a] - origin_[a]) * inv_bin_[a]), 0, bins_[a] - 1);
        hi[a] = std::clamp(static_cast<int>((b.max()[a] - origin_[a]) * inv_bin_[a]), 0, bins_[a] - 1);
      }
      for (int k = lo[2]; k <= hi[2]; ++k) {
        for (int j = lo[1]; j <= hi[1]; ++j) {
          const size_t row = (static_cast<size_t>(k) * bins_[1] + j) * bins_[0];
          for (int l = lo[0]; l <= hi[0]; ++l) {
            if (pass == 0) {
              ++start_[row + l + 1];
            } else {
              items_[cursor[row + l]++] = static_cast<uint32_t>(i);
            }
          }
        }
      }
    }
  }
}

std::span<const uint32_t> BoxGrid::At(const core::Vec3d& x, double slack) const {
  const int64_t bin = Bin(x, slack, nullptr);
  return bin < 0 ? std::span<const uint32_t>() : Items(bin);
}

int64_t BoxGrid::Locate(const core::Vec3d& x, core::Vec3d* within) const { return Bin(x, 0, within); }

int64_t BoxGrid::Bin(const core::Vec3d& x, double slack, core::Vec3d* within) const {
  if (start_.empty()) return -1;
  std::array<int, 3> cell;
  for (int a = 0; a < 3; ++a) {
    const double t = (x[a] - origin_[a]) * inv_bin_[a];
    if (!(t >= -slack) || t > bins_[a] + slack) return -1;
    cell[a] = std::clamp(static_cast<int>(t), 0, bins_[a] - 1);
    if (within != nullptr) (*within)[a] = std::clamp(t - cell[a], 0.0, 1.0 - 1e-9);
  }
  return (static_cast<int64_t>(cell[2]) * bins_[1] + cell[1]) * bins_[0] + cell[0];
}

}  // namespace lsqsurf::volume
