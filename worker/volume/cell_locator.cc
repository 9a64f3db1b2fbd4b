#include "worker/volume/cell_locator.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace lsqsurf::volume {
namespace {

// Barycentric coordinates of x in tetrahedron (a, b, c, d); false when it is degenerate.
bool Barycentric(const Vec3d& x, const Vec3d& a, const Vec3d& b, const Vec3d& c, const Vec3d& d,
                 std::array<double, 4>& w) {
  Eigen::Matrix3d m;
  m.col(0) = b - a;
  m.col(1) = c - a;
  m.col(2) = d - a;
  const double det = m.determinant();
  if (det == 0) return false;
  const Vec3d l = m.inverse() * (x - a);
  w = {1.0 - l.sum(), l[0], l[1], l[2]};
  return true;
}

}  // namespace

CellLocator::CellLocator(const VolumeMesh& mesh) : positions_(mesh.positions), tets_(Tetrahedralize(mesh)) {
  core::Box3 box;
  for (const Vec3f& p : positions_) box.extend(p.cast<double>());
  // About two tetrahedra per bin on average.
  const Vec3d size = box.sizes().cwiseMax(1e-30);
  const double bin = std::cbrt(size.prod() / std::max<double>(1.0, static_cast<double>(tets_.size()) / 2.0));
  for (int a = 0; a < 3; ++a) {
    bins_[a] = std::clamp(static_cast<int>(std::ceil(size[a] / bin)), 1, 1024);
    inv_bin_[a] = bins_[a] / size[a];
  }
  origin_ = box.min();
  const size_t bin_count = static_cast<size_t>(bins_[0]) * bins_[1] * bins_[2];
  auto bin_range = [&](const std::array<uint32_t, 4>& t, std::array<int, 3>& lo, std::array<int, 3>& hi) {
    Vec3d mn = positions_[t[0]].cast<double>(), mx = mn;
    for (int k = 1; k < 4; ++k) {
      mn = mn.cwiseMin(positions_[t[k]].cast<double>());
      mx = mx.cwiseMax(positions_[t[k]].cast<double>());
    }
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::clamp(static_cast<int>((mn[a] - origin_[a]) * inv_bin_[a]), 0, bins_[a] - 1);
      hi[a] = std::clamp(static_cast<int>((mx[a] - origin_[a]) * inv_bin_[a]), 0, bins_[a] - 1);
    }
  };
  // Two passes (count, fill) keep the bins in one CSR array.
  bin_start_.assign(bin_count + 1, 0);
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<uint32_t> cursor;
    if (pass == 1) {
      for (size_t b = 0; b < bin_count; ++b) bin_start_[b + 1] += bin_start_[b];
      bin_tets_.resize(bin_start_[bin_count]);
      cursor.assign(bin_start_.begin(), bin_start_.end() - 1);
    }
    std::array<int, 3> lo, hi;
    for (size_t t = 0; t < tets_.size(); ++t) {
      bin_range(tets_[t], lo, hi);
      for (int k = lo[2]; k <= hi[2]; ++k) {
        for (int j = lo[1]; j <= hi[1]; ++j) {
          for (int i = lo[0]; i <= hi[0]; ++i) {
            const size_t b = (static_cast<size_t>(k) * bins_[1] + j) * bins_[0] + i;
            if (pass == 0) {
              ++bin_start_[b + 1];
            } else {
              bin_tets_[cursor[b]++] = static_cast<uint32_t>(t);
            }
          }
        }
      }
    }
  }
}

CellLocator::Location CellLocator::Locate(const Vec3d& x) const {
  Location out;
  std::array<int, 3> cell;
  for (int a = 0; a < 3; ++a) {
    const double f = (x[a] - origin_[a]) * inv_bin_[a];
    // A point just outside the box may still be within the boundary tolerance of a cell.
    if (f < -1e-6 * bins_[a] || f > bins_[a] * (1 + 1e-6)) return out;
    cell[a] = std::clamp(static_cast<int>(f), 0, bins_[a] - 1);
  }
  const size_t b = (static_cast<size_t>(cell[2]) * bins_[1] + cell[1]) * bins_[0] + cell[0];
  double best = -1e300;
  for (uint32_t e = bin_start_[b]; e < bin_start_[b + 1]; ++e) {
    const auto& t = tets_[bin_tets_[e]];
    std::array<double, 4> w;
    if (!Barycentric(x, positions_[t[0]].cast<double>(), positions_[t[1]].cast<double>(),
                     positions_[t[2]].cast<double>(), positions_[t[3]].cast<double>(), w)) {
      continue;
    }
    const double smallest = *std::min_element(w.begin(), w.end());
    if (smallest >= 0) {
      out.tet = bin_tets_[e];
      out.weights = w;
      return out;
    }
    // Remember the nearest miss: points on the boundary fall just outside by rounding.
    if (smallest > best) {
      best = smallest;
      out.tet = bin_tets_[e];
      out.weights = w;
    }
  }
  if (best < -1e-6) return Location{};
  return out;
}

double CellLocator::Interpolate(std::span<const float> values, int components, int component,
                                const Location& at) const {
  const auto& t = tets_[at.tet];
  double v = 0;
  for (int k = 0; k < 4; ++k) v += at.weights[k] * values[static_cast<size_t>(t[k]) * components + component];
  return v;
}

}  // namespace lsqsurf::volume
