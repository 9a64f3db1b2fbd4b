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

CellLocator::CellLocator(const VolumeMesh& mesh) : CellLocator(mesh.positions, Tetrahedralize(mesh)) {}

CellLocator::CellLocator(std::vector<Vec3f> positions, std::vector<std::array<uint32_t, 4>> tets)
    : positions_(std::move(positions)), tets_(std::move(tets)) {
  core::Box3 bounds;
  for (const Vec3f& p : positions_) bounds.extend(p.cast<double>());
  // About two tetrahedra per bin on average.
  const double bin =
      std::cbrt(bounds.sizes().cwiseMax(1e-30).prod() / std::max<double>(1.0, static_cast<double>(tets_.size()) / 2.0));
  grid_ = BoxGrid(bounds, Vec3d::Constant(bin), 1 << 30, tets_.size(), [&](size_t t) {
    core::Box3 box;
    for (uint32_t v : tets_[t]) box.extend(positions_[v].cast<double>());
    return box;
  });
}

CellLocator::Location CellLocator::Locate(const Vec3d& x) const {
  Location out;
  // A point just outside the grid may still be within the boundary tolerance of a cell.
  const std::span<const uint32_t> candidates = grid_.At(x, 1e-6);
  double best = -1e300;
  for (uint32_t candidate : candidates) {
    const auto& t = tets_[candidate];
    std::array<double, 4> w;
    if (!Barycentric(x, positions_[t[0]].cast<double>(), positions_[t[1]].cast<double>(),
                     positions_[t[2]].cast<double>(), positions_[t[3]].cast<double>(), w)) {
      continue;
    }
    const double smallest = *std::min_element(w.begin(), w.end());
    if (smallest >= 0) {
      out.tet = candidate;
      out.weights = w;
      return out;
    }
    // Remember the nearest miss: points on the boundary fall just outside by rounding.
    if (smallest > best) {
      best = smallest;
      out.tet = candidate;
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
