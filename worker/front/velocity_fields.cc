#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/front/front_internal.h"
#include "worker/front/front_tracking.h"

namespace lsqsurf::front {
namespace {

class ZalesakField final : public VelocityField {
 public:
  Vec3d At(const Vec3d& x, double) const override {
    constexpr double w = std::numbers::pi / 314.0;
    return {w * (0.5 - x.y()), w * (x.x() - 0.5), 0.0};
  }
};

class EnrightField final : public VelocityField {
 public:
  EnrightField(double period, TimeModulation modulation) : period_(period), modulation_(modulation) {}
  double Modulation(double t) const {
    if (modulation_ == TimeModulation::kCosine) return std::cos(std::numbers::pi * t / period_);
    const double from_half = t - 0.5 * period_;
    if (std::abs(from_half) <= 1e-9 * period_) return 0;
    return from_half < 0 ? 1 : -1;
  }
  Vec3d At(const Vec3d& p, double t) const override {
    const double pi = std::numbers::pi, c = Modulation(t);
    const double sx = std::sin(pi * p.x()), sy = std::sin(pi * p.y()), sz = std::sin(pi * p.z());
    const double s2x = std::sin(2 * pi * p.x()), s2y = std::sin(2 * pi * p.y()), s2z = std::sin(2 * pi * p.z());
    return {2 * sx * sx * s2y * s2z * c, -s2x * sy * sy * s2z * c, -s2x * s2y * sz * sz * c};
  }

 private:
  double period_;
  TimeModulation modulation_;
};

class GridField final : public VelocityField {
 public:
  GridField(Vec3d origin, Vec3d spacing, int nx, int ny, int nz, std::vector<Vec3d> values)
      : origin_(origin), spacing_(spacing), n_{nx, ny, nz}, values_(std::move(values)) {}
  Vec3d At(const Vec3d& x, double) const override {
    std::array<int, 3> i0{};
    std::array<double, 3> f{};
    for (int a = 0; a < 3; ++a) {
      const double g = std::clamp((x[a] - origin_[a]) / spacing_[a], 0.0, static_cast<double>(n_[a] - 1));
      i0[a] = std::min(static_cast<int>(g), std::max(0, n_[a] - 2));
      f[a] = n_[a] > 1 ? g - i0[a] : 0.0;
    }
    Vec3d v = Vec3d::Zero();
    for (int corner = 0; corner < 8; ++corner) {
      double w = 1;
      std::array<int, 3> i{};
      for (int a = 0; a < 3; ++a) {
        const int bit = (corner >> a) & 1;
        i[a] = std::min(i0[a] + bit, n_[a] - 1);
        w *= bit ? f[a] : 1 - f[a];
      }
      if (w == 0) continue;
      v += w * values_[static_cast<size_t>(i[0]) +
                       static_cast<size_t>(n_[0]) *
                           (static_cast<size_t>(i[1]) + static_cast<size_t>(n_[1]) * static_cast<size_t>(i[2]))];
    }
    return v;
  }

 private:
  Vec3d origin_;
  Vec3d spacing_;
  std::array<int, 3> n_;
  std::vector<Vec3d> values_;
};

}  // namespace

// The largest eigenvalue of the symmetric part of ∇v: the fastest rate at which the flow pulls
// two nearby points apart (d|δ|/dt ≤ λ|δ|).
double LargestStrainRate(const Eigen::Matrix3d& jacobian) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
  solver.computeDirect(0.5 * (jacobian + jacobian.transpose()), Eigen::EigenvaluesOnly);
  return solver.eigenvalues()(2);
}

void RaiseTo(std::atomic<double>& most, double value) {
  double seen = most.load();
  while (value > seen && !most.compare_exchange_weak(seen, value)) {
  }
}

// Flow Jacobian ∇v by central differences (the fields are smooth; the step only has to be far
// below their length scale and far above rounding).
Eigen::Matrix3d Jacobian(const VelocityField& v, const Vec3d& x, double t) {
  constexpr double eps = 1e-6;
  Eigen::Matrix3d j;
  for (int a = 0; a < 3; ++a) {
    const Vec3d e = Vec3d::Unit(a) * eps;
    j.col(a) = (v.At(x + e, t) - v.At(x - e, t)) / (2 * eps);
  }
  return j;
}

Vec3d Rk4Step(const VelocityField& v, const Vec3d& x, double t, double dt) {
  const Vec3d k1 = v.At(x, t);
  const Vec3d k2 = v.At(x + 0.5 * dt * k1, t + 0.5 * dt);
  const Vec3d k3 = v.At(x + 0.5 * dt * k2, t + 0.5 * dt);
  const Vec3d k4 = v.At(x + dt * k3, t + dt);
  return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4);
}

std::unique_ptr<VelocityField> ZalesakRotation() { return std::make_unique<ZalesakField>(); }
std::unique_ptr<VelocityField> EnrightDeformation(double period, TimeModulation modulation) {
  return std::make_unique<EnrightField>(period, modulation);
}

absl::StatusOr<std::unique_ptr<VelocityField>> GridVelocity(Vec3d origin, Vec3d spacing, int nx, int ny, int nz,
                                                            std::vector<Vec3d> values) {
  if (!origin.allFinite() || !spacing.allFinite() || !(spacing.minCoeff() > 0)) {
    return absl::InvalidArgumentError("the velocity grid needs a finite origin and a positive spacing along each axis");
  }
  if (nx < 1 || ny < 1 || nz < 1 || static_cast<int64_t>(nx) * ny * nz > 256LL * 256 * 256) {
    return absl::InvalidArgumentError("the velocity grid must have 1..256³ nodes");
  }
  if (values.size() != static_cast<size_t>(nx) * static_cast<size_t>(ny) * static_cast<size_t>(nz)) {
    return absl::InvalidArgumentError(core::StrCat(
        "the velocity grid has ", values.size(), " vectors, expected nx·ny·nz = ", static_cast<int64_t>(nx) * ny * nz));
  }
  for (size_t i = 0; i < values.size(); ++i) {
    if (!values[i].allFinite()) return absl::InvalidArgumentError(core::StrCat("velocity ", i, " is not finite"));
  }
  return std::make_unique<GridField>(origin, spacing, nx, ny, nz, std::move(values));
}

}  // namespace lsqsurf::front
