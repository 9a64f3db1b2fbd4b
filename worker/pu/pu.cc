#include <algorithm>
#include <array>
#include <cmath>

#include "worker/core/strings.h"
#include "worker/pu/pu_internal.h"

namespace lsqsurf::pu {

const core::ParamTable<PuParams>& PuParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuParams>();
    t->Real<&PuParams::error_threshold>("error_threshold", kMinErrorThreshold, 0.1, "share of the diagonal",
                                        "largest fitting error accepted in a cell; set it near the noise amplitude "
                                        "for noisy scans")
        .Integer<&PuParams::max_depth>("max_depth", 1, 18, "levels", "octree levels below the root cube")
        .Integer<&PuParams::max_degree>("max_degree", 0, kMaxDegree, "", "highest polynomial degree of a local fit")
        .Real<&PuParams::support_factor>("support_factor", 0.55, 2, "cell diagonals", "support radius of a cell")
        .Integer<&PuParams::min_points>("min_points", 4, 200, "points",
                                        "the fitting ball of a sparse cell grows until it holds this many points")
        .Real<&PuParams::max_normal_angle>("max_normal_angle", 10, 180, "degrees",
                                           "normal-cone criterion: wider cells are split (180 disables it)")
        .Flag<&PuParams::coverage_check>("coverage", "coverage criteria: no sheets away from the data, holes stay open")
        .Real<&PuParams::coverage_factor>("coverage_factor", 0.5, 20, "local spacings",
                                          "surface only within this many local spacings (distance to the 8th "
                                          "neighbour) of a data point")
        .Flag<&PuParams::orientation_check>("orientation_check",
                                            "reject fits whose gradient opposes their points' normals")
        .Real<&PuParams::noise_level>("noise_level", 0, 0.1, "share of the diagonal",
                                      "scan noise sigma; 0 declares the data exact; above error_threshold the "
                                      "threshold becomes 3 sigma and min_points at least 80")
        .Or(-1, "estimated from the data")
        .Flag<&PuParams::sharp>("sharp",
                                "sharp edges and corners: where a cell's smooth fit fails and its normals split "
                                "into clusters, one sheet per cluster combined by max/min")
        .Real<&PuParams::sharp_angle>("sharp_angle", 5, 90, "degrees",
                                      "normals of one cell wider apart than this show an edge");
    return t;
  }();
  return *table;
}

absl::Status Validate(const PuParams& p) { return PuParamTable().Validate(p); }

const core::ParamTable<PuExtractParams>& PuExtractParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuExtractParams>();
    t->Real<&PuExtractParams::cell_size>("cell_size", 0.25, 64, "mean point spacings",
                                         "smallest extraction cell at the surface (rounded to an octree level); cells "
                                         "near the data are up to 8x larger where the surface is flat enough");
    t->Real<&PuExtractParams::chord_error>("chord_error", 0, 0.01, "share of the diagonal",
                                           "cells are split towards cell_size where flat triangles would stray "
                                           "farther than this from the surface; 0 = finest cells everywhere");
    t->Include(&PuExtractParams::marching, extract::MarchingParamTable());
    return t;
  }();
  return *table;
}

PuFunction::PuFunction(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
const PuStats& PuFunction::stats() const { return impl_->stats; }
PuFunction::~PuFunction() = default;

core::FieldValue PuFunction::Value(const Vec3d& x) const {
  const core::FieldGradient g = impl_->Evaluate(x, false);
  return {g.value, g.defined};
}

double PuFunction::ValueOnly(const Vec3d& x) const { return impl_->Evaluate(x, false, false).value; }

core::FieldGradient PuFunction::ValueAndGradient(const Vec3d& x) const { return impl_->Evaluate(x, true); }

core::FieldGradient PuFunction::ValueAndGradientOnly(const Vec3d& x) const {
  core::FieldGradient g = impl_->Evaluate(x, true, false);
  g.defined = std::isfinite(g.value);
  return g;
}

FitLabel PuFunction::DominantFit(const Vec3d& x) const {
  FitLabel label;
  double best = 0;
  impl_->ForEachSupport(x, [&](const LocalFit& fit, double s2) {
    if (const double theta = Theta(s2); theta > best) {
      best = theta;
      label = {fit.depth, fit.degree, static_cast<int>(fit.feature)};
    }
  });
  return label;
}

std::span<const Vec3f> PuFunction::points() const { return impl_->cloud->positions; }

core::FieldGradient PuFunction::ValueOrDataSide(const Vec3d& x, bool with_gradient) const {
  const Impl& m = *impl_;
  auto fitted = [&] {
    core::FieldGradient g = m.Evaluate(x, with_gradient, false);
    g.defined = std::isfinite(g.value);
    return g;
  };
  if (!m.coverage_check) return fitted();
  const Impl::Coverage coverage = m.CoverageAt(x);
  if (coverage.covered) return fitted();
  const uint32_t nearest = coverage.nearest.index;
  const Vec3d d = x - m.cloud->positions[nearest].cast<double>();
  const double side = d.dot(m.cloud->normals[nearest].cast<double>()) >= 0 ? 1.0 : -1.0;
  const double length = d.norm();
  core::FieldGradient g;
  g.value = side * length;
  if (with_gradient && length > 0) g.gradient = side * d / length;
  return g;
}

PuFunction::Impl::Coverage PuFunction::Impl::CoverageAt(const Vec3d& x) const {
  Coverage out{cloud->kd_tree->Nearest(x.cast<float>())};
  const double reach = coverage_factor * cloud->local_spacing[out.nearest.index];
  const double rim_reach = rim_reach_share * reach;
  out.covered =
      out.nearest.distance2 <= reach * reach &&
      (rim_reach_share >= 1 || out.nearest.distance2 <= rim_reach * rim_reach || !BeyondRim(x, kRimReadFactor * reach));
  return out;
}

bool PuFunction::Impl::BeyondRim(const Vec3d& x, double radius) const {
  thread_local std::vector<core::Neighbor> near;  // Reused: extraction asks this in its inner loops.
  cloud->kd_tree->Knn(x.cast<float>(), kRimNeighbors, near);
  const double radius2 = radius * radius;
  Vec3d normal = Vec3d::Zero();
  size_t count = 0;
  for (const core::Neighbor& n : near) {
    if (n.distance2 > radius2) break;
    normal += cloud->normals[n.index].cast<double>();
    ++count;
  }
  if (count < 3) return true;
  // Normals that disagree (a thin part's tip, a crease, both sides of a thin wall) give no plane
  // to look in: treated as surrounded, which is the full reach's behaviour.
  if (normal.norm() < kRimNormalAgreement * static_cast<double>(count)) return false;
  normal.normalize();
  const Vec3d u = normal.unitOrthogonal(), v = normal.cross(u);
  std::array<double, kRimNeighbors> angles{};
  size_t m = 0;
  for (size_t k = 0; k < count; ++k) {
    const Vec3d d = cloud->positions[near[k].index].cast<double>() - x;
    const double du = d.dot(u), dv = d.dot(v);
    if (du * du + dv * dv > 1e-24 * radius2) angles[m++] = std::atan2(dv, du);
  }
  if (m < 3) return true;
  std::sort(angles.begin(), angles.begin() + static_cast<std::ptrdiff_t>(m));
  double gap = angles[0] + 2 * M_PI - angles[m - 1];
  for (size_t k = 1; k < m; ++k) gap = std::max(gap, angles[k] - angles[k - 1]);
  return gap > kRimGap;
}

void PuFunction::KeepFullReachPastRims() { impl_->rim_reach_share = 1; }

bool PuFunction::NearCrease(const Vec3d& x) const {
  bool crease = false;
  impl_->ForEachSupport(x, [&](const LocalFit& fit, double) { crease |= fit.feature != Feature::kSmooth; });
  return crease;
}

}  // namespace lsqsurf::pu
