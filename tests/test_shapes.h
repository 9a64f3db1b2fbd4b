// tests/test_shapes.h — analytic shapes shared by the tests: exact samples, normals, volumes.
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <numbers>
#include <random>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/core/sphere_mesh.h"

namespace lsqsurf::testing {

// Fibonacci lattice on a sphere: near-uniform samples with exact outward normals.
inline core::PointCloud SphereCloud(size_t n, double radius = 1.0, core::Vec3d center = core::Vec3d::Zero()) {
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

// The cap of the unit sphere within `polar` radians of +z, sampled uniformly at random by area,
// one point per spacing²: an open sheet with a rim, as a single view sees a ball. Exact normals.
inline core::PointCloud CapCloud(double polar, double spacing, uint64_t seed = 3) {
  const auto n = static_cast<size_t>(2 * std::numbers::pi * (1 - std::cos(polar)) / (spacing * spacing));
  core::PointCloud cloud;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0, 1);
  for (size_t i = 0; i < n; ++i) {
    const double z = 1 - unit(rng) * (1 - std::cos(polar)), angle = 2 * std::numbers::pi * unit(rng);
    const double r = std::sqrt(1 - z * z);
    cloud.positions.push_back(core::Vec3d(r * std::cos(angle), r * std::sin(angle), z).cast<float>());
    cloud.normals.push_back(cloud.positions.back());
  }
  return cloud;
}

// A wavy strip z = amplitude·sin(3x) over [0, length] × [0, width], sampled uniformly at random
// in x and y: a long open sheet with a rim all round, as a single view sees a wall. Exact normals.
inline core::PointCloud WavyStripCloud(size_t n, double length, double width, double amplitude = 0.05,
                                       uint64_t seed = 4) {
  core::PointCloud cloud;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0, 1);
  for (size_t i = 0; i < n; ++i) {
    const double x = length * unit(rng), y = width * unit(rng);
    cloud.positions.push_back(core::Vec3d(x, y, amplitude * std::sin(3 * x)).cast<float>());
    cloud.normals.push_back(core::Vec3d(-3 * amplitude * std::cos(3 * x), 0, 1).normalized().cast<float>());
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

// A CAD-like part: the block [-a, a] x [-b, b] x [-c, c] drilled through along z by a hole of
// radius `hole` at the origin, sampled uniformly by area (sharp edges, flat faces, a genus-1
// surface); exact outward normals. Volume 8abc - 2c * pi * hole^2.
inline core::PointCloud DrilledBlockCloud(size_t n, double a = 1.0, double b = 0.6, double c = 0.3, double hole = 0.3,
                                          uint64_t seed = 11) {
  core::PointCloud cloud;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const double pi = std::numbers::pi;
  // Areas: top+bottom (minus the hole), x faces, y faces, the hole's wall.
  const double areas[4] = {2 * (4 * a * b - pi * hole * hole), 2 * 4 * b * c, 2 * 4 * a * c, 2 * pi * hole * 2 * c};
  const double total = areas[0] + areas[1] + areas[2] + areas[3];
  auto emit = [&](core::Vec3d p, core::Vec3d normal) {
    cloud.positions.push_back(p.cast<float>());
    cloud.normals.push_back(normal.cast<float>());
  };
  while (cloud.size() < n) {
    double pick = u(rng) * total;
    const double sign = u(rng) < 0.5 ? -1 : 1;
    if ((pick -= areas[0]) < 0) {
      const core::Vec3d p((2 * u(rng) - 1) * a, (2 * u(rng) - 1) * b, sign * c);
      if (p.x() * p.x() + p.y() * p.y() < hole * hole) continue;
      emit(p, {0, 0, sign});
    } else if ((pick -= areas[1]) < 0) {
      emit({sign * a, (2 * u(rng) - 1) * b, (2 * u(rng) - 1) * c}, {sign, 0, 0});
    } else if ((pick -= areas[2]) < 0) {
      emit({(2 * u(rng) - 1) * a, sign * b, (2 * u(rng) - 1) * c}, {0, sign, 0});
    } else {
      const double t = 2 * pi * u(rng);
      const core::Vec3d radial(std::cos(t), std::sin(t), 0);
      emit(hole * radial + core::Vec3d(0, 0, (2 * u(rng) - 1) * c), -radial);  // Faces into the hole.
    }
  }
  return cloud;
}

// A torus around z, sampled on a regular (θ, φ) grid with arc steps of about `step`, with
// exact normals: close to the gridline samples of front tracking, and free of random gaps.
inline core::PointCloud TorusGridCloud(double R, double r, double step) {
  core::PointCloud cloud;
  const int around = static_cast<int>(std::ceil(2 * std::numbers::pi * (R + r) / step));
  const int tube = static_cast<int>(std::ceil(2 * std::numbers::pi * r / step));
  for (int i = 0; i < around; ++i) {
    const double theta = 2 * std::numbers::pi * i / around;
    for (int j = 0; j < tube; ++j) {
      const double phi = 2 * std::numbers::pi * (j + 0.5 * (i % 2)) / tube;
      const core::Vec3d n(std::cos(phi) * std::cos(theta), std::cos(phi) * std::sin(theta), std::sin(phi));
      const core::Vec3d c(R * std::cos(theta), R * std::sin(theta), 0);
      cloud.positions.push_back((c + r * n).cast<float>());
      cloud.normals.push_back(n.cast<float>());
    }
  }
  return cloud;
}

// Largest distance, along the exact normal, from probe points of the true torus to the zero
// set of F (found by bisection within ±h).
inline double MaxTorusError(const core::ImplicitFunction& f, double R, double r, double h, int probes) {
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> angle(0, 2 * std::numbers::pi);
  double worst = 0;
  for (int k = 0; k < probes; ++k) {
    const double theta = angle(rng), phi = angle(rng);
    const core::Vec3d n(std::cos(phi) * std::cos(theta), std::cos(phi) * std::sin(theta), std::sin(phi));
    const core::Vec3d p = core::Vec3d(R * std::cos(theta), R * std::sin(theta), 0) + r * n;
    double lo = -h, hi = h;
    EXPECT_LT(f.Value(p + lo * n).value, 0);
    EXPECT_GT(f.Value(p + hi * n).value, 0);
    for (int i = 0; i < 60; ++i) {
      const double mid = 0.5 * (lo + hi);
      (f.Value(p + mid * n).value < 0 ? lo : hi) = mid;
    }
    worst = std::max(worst, std::abs(0.5 * (lo + hi)));
  }
  return worst;
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
  double Distance(const core::Vec3d& x) const { return std::hypot(std::hypot(x.x(), x.y()) - R_, x.z()) - r_; }

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

// A palm (sphere of radius 0.3) with capsule fingers down to 2.5 point spacings thick, two of
// them side by side: the union's surface sampled uniformly by area with exact normals.
struct Capsule {
  core::Vec3d a, b;
  double r;
  double Distance(const core::Vec3d& x) const {
    const core::Vec3d ab = b - a;
    const double t = std::clamp((x - a).dot(ab) / ab.squaredNorm(), 0.0, 1.0);
    return (x - (a + t * ab)).norm() - r;
  }
};

inline core::PointCloud HandCloud(double spacing, std::vector<Capsule>& fingers) {
  fingers = {{core::Vec3d(0, 0.25, 0), core::Vec3d(0, 0.7, 0), 0.006},
             {core::Vec3d(0.1, 0.2, 0), core::Vec3d(0.3, 0.6, 0), 0.008},
             {core::Vec3d(-0.1, 0.2, 0), core::Vec3d(-0.3, 0.6, 0), 0.005},
             {core::Vec3d(0.2, 0.1, 0), core::Vec3d(0.6, 0.2, 0), 0.01},
             {core::Vec3d(0.2, 0.1, 0.03), core::Vec3d(0.6, 0.2, 0.03), 0.01}};
  const double palm = 0.3;
  auto inside_other = [&](const core::Vec3d& x, int self) {
    if (self != -1 && x.norm() < palm - 1e-9) return true;
    for (int i = 0; i < static_cast<int>(fingers.size()); ++i) {
      if (i != self && fingers[static_cast<size_t>(i)].Distance(x) < -1e-9) return true;
    }
    return false;
  };
  core::PointCloud cloud;
  std::mt19937_64 rng(5);
  std::normal_distribution<double> gauss(0, 1);
  std::uniform_real_distribution<double> unit(0, 1);
  // About one point per spacing² of area (the mean nearest-neighbour distance is then ~0.5 of it).
  auto count = [&](double area) { return static_cast<size_t>(area / (spacing * spacing)); };
  auto emit = [&](const core::Vec3d& x, const core::Vec3d& n, int self) {
    if (inside_other(x, self)) return;
    cloud.positions.push_back(x.cast<float>());
    cloud.normals.push_back(n.cast<float>());
  };
  auto sphere = [&](const core::Vec3d& c, double r, int self) {
    for (size_t i = count(4 * std::numbers::pi * r * r); i > 0; --i) {
      const core::Vec3d d = core::Vec3d(gauss(rng), gauss(rng), gauss(rng)).normalized();
      emit(c + r * d, d, self);
    }
  };
  sphere(core::Vec3d::Zero(), palm, -1);
  for (int i = 0; i < static_cast<int>(fingers.size()); ++i) {
    const Capsule& f = fingers[static_cast<size_t>(i)];
    const core::Vec3d axis = (f.b - f.a).normalized(), u = axis.unitOrthogonal(), v = axis.cross(u);
    const double length = (f.b - f.a).norm();
    for (size_t k = count(2 * std::numbers::pi * f.r * length); k > 0; --k) {
      const double angle = 2 * std::numbers::pi * unit(rng);
      const core::Vec3d radial = std::cos(angle) * u + std::sin(angle) * v;
      emit(f.a + unit(rng) * length * axis + f.r * radial, radial, i);
    }
    // Whole end spheres; their inner halves lie inside the capsule itself and are dropped.
    for (const core::Vec3d& end : {f.a, f.b}) {
      for (size_t k = count(4 * std::numbers::pi * f.r * f.r); k > 0; --k) {
        const core::Vec3d d = core::Vec3d(gauss(rng), gauss(rng), gauss(rng)).normalized();
        if (f.Distance(end + f.r * d) < -1e-9) continue;
        emit(end + f.r * d, d, i);
      }
    }
  }
  return cloud;
}

// How BallOnATableView's camera measures. Where `step` > 0, the depths come back quantized as a
// sensor's do: along the view's axis to whole multiples of `step` in inverse depth (a stereo
// rig's disparity steps) or, with `range_steps`, the distance from the eye to whole multiples of
// `step` (a time-of-flight camera's).
struct ViewOptions {
  int scale = 1;  // Pixels: 160 × 120 times this in each direction.
  double step = 0;
  bool range_steps = false;
};

// A depth camera's view of a ball on a table: rays from `eye` through a 160 x 120 grid (ViewOptions), each
// kept at its first hit, with the surface's normal there (toward the camera, as every surface a
// camera sees is). Rays that hit nothing are missing pixels.
// The normals stay the true surface's where the depths are quantized.
inline core::PointCloud BallOnATableView(const core::Vec3d& eye, const ViewOptions& options = {}) {
  core::PointCloud cloud;
  const core::Vec3d centre(0, 0, 0.3), forward = (centre - eye).normalized();
  const core::Vec3d right = forward.cross(core::Vec3d::UnitZ()).normalized(), up = right.cross(forward);
  const double radius = 0.3;
  const int rows = 120 * options.scale, columns = 160 * options.scale;
  for (int row = 0; row < rows; ++row) {
    for (int column = 0; column < columns; ++column) {
      const core::Vec3d ray = (forward + 0.6 * ((column + 0.5) / (columns / 2.0) - 1) * right +
                               0.45 * ((row + 0.5) / (rows / 2.0) - 1) * up)
                                  .normalized();
      double nearest = std::numeric_limits<double>::infinity();
      core::Vec3d normal = core::Vec3d::Zero();
      const core::Vec3d to_eye = eye - centre;  // The ball: |eye + t ray - centre| = radius.
      const double b = ray.dot(to_eye), c = to_eye.squaredNorm() - radius * radius;
      if (const double disc = b * b - c; disc > 0 && -b - std::sqrt(disc) > 0) {
        nearest = -b - std::sqrt(disc);
        normal = (eye + nearest * ray - centre).normalized();
      }
      if (ray.z() < 0) {  // The table, z = 0, within 1.5 of the ball.
        const double t = -eye.z() / ray.z();
        const core::Vec3d hit = eye + t * ray;
        if (t < nearest && std::abs(hit.x()) < 1.5 && std::abs(hit.y()) < 1.5) {
          nearest = t;
          normal = core::Vec3d::UnitZ();
        }
      }
      if (!std::isfinite(nearest)) continue;
      if (options.step > 0 && options.range_steps) {
        nearest = std::round(nearest / options.step) * options.step;
      } else if (options.step > 0) {
        const double along = ray.dot(forward), z = nearest * along;
        nearest = 1.0 / (std::round(1.0 / z / options.step) * options.step) / along;
      }
      cloud.positions.push_back((eye + nearest * ray).cast<float>());
      cloud.normals.push_back(normal.cast<float>());
    }
  }
  return cloud;
}

}  // namespace lsqsurf::testing
