// tests/test_shapes.h — analytic shapes shared by the tests: exact samples, normals, volumes.
#pragma once

#include <cmath>
#include <memory>
#include <numbers>
#include <random>

#include <gtest/gtest.h>

#include "worker/core/geometry.h"
#include "absl/status/statusor.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "tests/sphere_mesh.h"

namespace lsqsurf::testing {

// Fibonacci lattice on a sphere: near-uniform samples with exact outward normals.
inline core::PointCloud SphereCloud(size_t n, double radius = 1.0,
                                    core::Vec3d center = core::Vec3d::Zero()) {
  core::PointCloud cloud;
  const double golden = std::numbers::pi * (3.0 - std::sqrt(5.0));
  for (size_t i = 0; i < n; ++i) {
    const double z = 1.0 - 2.0 * (static_cast<double>(i) + 0.5) / static_cast<double>(n);
    const double r = std::sqrt(1.0 - z * z), phi = golden * static_cast<double>(i);
    const core::Vec3d d(r * std::cos(phi), r * std::sin(phi), z);
    cloud.positions.push_back((center + radius * d).cast<float>());
    cloud.normals.push_back(d.cast<float>());
  }
  return cloud;
}

// Torus around the z axis (tube radius r, centre-line radius R), sampled uniformly by area by
// rejection; exact outward normals.
inline core::PointCloud TorusCloud(size_t n, double R, double r, uint64_t seed = 5) {
  core::PointCloud cloud;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  while (cloud.size() < n) {
    const double theta = 2 * std::numbers::pi * u(rng), phi = 2 * std::numbers::pi * u(rng);
    // Area element ∝ R + r cos(phi).
    if (u(rng) * (R + r) > R + r * std::cos(phi)) continue;
    const core::Vec3d n3(std::cos(phi) * std::cos(theta), std::cos(phi) * std::sin(theta), std::sin(phi));
    const core::Vec3d c(R * std::cos(theta), R * std::sin(theta), 0);
    cloud.positions.push_back((c + r * n3).cast<float>());
    cloud.normals.push_back(n3.cast<float>());
  }
  return cloud;
}

class SphereField : public core::ImplicitFunction {
 public:
  explicit SphereField(double radius) : radius_(radius) {}
  core::FieldValue Value(const core::Vec3d& x) const override { return {x.norm() - radius_, true}; }
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override {
    return {x.norm() - radius_, x.normalized(), true};
  }

 private:
  double radius_;
};

class TorusField : public core::ImplicitFunction {
 public:
  TorusField(double R, double r) : R_(R), r_(r) {}
  core::FieldValue Value(const core::Vec3d& x) const override { return {Distance(x), true}; }
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override {
    const double q = std::hypot(x.x(), x.y());
    const core::Vec3d ring(R_ * x.x() / q, R_ * x.y() / q, 0);
    return {Distance(x), (x - ring).normalized(), true};
  }
  double Distance(const core::Vec3d& x) const {
    return std::hypot(std::hypot(x.x(), x.y()) - R_, x.z()) - r_;
  }

 private:
  double R_, r_;
};

// Largest |F| / |∇F| (a first-order distance to the zero set) at `samples` random points of the
// true surface, given by `project` (maps a unit direction to a surface point). Every such point
// must be where F is defined.
template <class Project>
double MaxSurfaceError(const core::ImplicitFunction& f, Project project, int samples) {
  std::mt19937_64 rng(17);
  std::normal_distribution<double> g(0, 1);
  double worst = 0;
  for (int i = 0; i < samples; ++i) {
    const core::Vec3d x = project(core::Vec3d(g(rng), g(rng), g(rng)).normalized());
    const core::FieldGradient v = f.ValueAndGradient(x);
    EXPECT_TRUE(v.defined) << x.transpose();
    worst = std::max(worst, std::abs(v.value) / v.gradient.norm());
  }
  return worst;
}

// Runs an engine's builder (BuildPu, BuildIamls, …) and fails the test on an error; nullptr then.
template <typename Function, typename Params>
std::unique_ptr<Function> BuildOrFail(absl::StatusOr<std::unique_ptr<Function>> (*build)(const core::PointCloud&,
                                                                                          const Params&,
                                                                                          core::JobContext&),
                                      const core::PointCloud& cloud, const Params& params) {
  core::LocalJobContext ctx;
  auto f = build(cloud, params, ctx);
  EXPECT_TRUE(f.ok()) << f.status();
  return f.ok() ? *std::move(f) : nullptr;
}

}  // namespace lsqsurf::testing
