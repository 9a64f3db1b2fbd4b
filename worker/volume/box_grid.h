// worker/volume/box_grid.h — a uniform grid of bins listing the boxes that overlap each bin
// (compressed rows): the index behind the cell locator (tetrahedra) and the field's evaluation
// (kernel supports). Queries are const and thread-safe.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "worker/core/geometry.h"

namespace lsqsurf::volume {

class BoxGrid {
 public:
  BoxGrid() = default;
  // `count` boxes, box(i) giving the i-th; the grid covers `bounds` with bins of about
  // `bin_size` per axis, at most `max_bins` bins in all (larger bins beyond that).
  BoxGrid(const core::Box3& bounds, const core::Vec3d& bin_size, double max_bins, size_t count,
          const std::function<core::Box3(size_t)>& box);

  // The boxes whose bins hold x; empty outside the grid (a margin of `slack` bins counts as
  // inside, clamped to the border bins).
  std::span<const uint32_t> At(const core::Vec3d& x, double slack = 0) const;
  // The bin that holds x (−1 outside the grid) and, in `within`, where in that bin ([0, 1)³).
  int64_t Locate(const core::Vec3d& x, core::Vec3d* within = nullptr) const;
  std::span<const uint32_t> Items(int64_t bin) const {
    return {items_.data() + start_[bin], start_[bin + 1] - start_[bin]};
  }

 private:
  // At and Locate: the bin of x, a margin of `slack` bins counting as inside; −1 outside.
  int64_t Bin(const core::Vec3d& x, double slack, core::Vec3d* within) const;

  core::Vec3d origin_ = core::Vec3d::Zero();
  core::Vec3d inv_bin_ = core::Vec3d::Zero();
  std::array<int, 3> bins_ = {1, 1, 1};
  std::vector<uint32_t> start_;  // Items of bin b: items_[start_[b] .. start_[b + 1]).
  std::vector<uint32_t> items_;
};

}  // namespace lsqsurf::volume
