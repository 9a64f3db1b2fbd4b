// tests/polyhedra.h — exact convex polyhedra for the crease tests: fields, samples, distances.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <utility>
#include <vector>

#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/surface_distance.h"

namespace lsqsurf::testing {

using core::FieldGradient;
using core::FieldValue;
using core::TriangleMesh;
using core::Vec3d;
using core::Vec3f;

// max_k (n_k·y − offset_k) over planes, in a frame turned so that nothing lines up with the grid:
// a convex polyhedron, exact distance inside and a lower bound outside.
class TurnedPolyhedron : public core::ImplicitFunction {
 public:
  TurnedPolyhedron(std::vector<Vec3d> normals, double offset)
      : normals_(std::move(normals)),
        offset_(offset),
        rotation_(Eigen::AngleAxisd(0.37, Vec3d(1, 2, 3).normalized()).toRotationMatrix()) {}

  FieldValue Value(const Vec3d& x) const override { return {Evaluate(x, nullptr), true}; }
  FieldGradient ValueAndGradient(const Vec3d& x) const override {
    Vec3d g = Vec3d::Zero();
    const double v = Evaluate(x, &g);
    return {v, g, true};
  }
  // World coordinates of a point given in the polyhedron's own frame.
  Vec3d World(const Vec3d& local) const { return rotation_ * local + kCentre; }

  // Points evenly spread over the faces (all of equal area here), with exact normals: points of
  // a box projected onto a random face's plane, kept where that face is the surface.
  core::PointCloud Sample(size_t count, uint64_t seed = 9) const {
    core::PointCloud cloud;
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> coordinate(-1, 1);
    std::uniform_int_distribution<size_t> face(0, normals_.size() - 1);
    while (cloud.positions.size() < count) {
      const Vec3d& n = normals_[face(rng)];
      Vec3d y(coordinate(rng), coordinate(rng), coordinate(rng));
      y -= (n.dot(y) - offset_) * n;
      bool on_face = true;
      for (const Vec3d& m : normals_) on_face &= m.dot(y) - offset_ <= 1e-12;
      if (!on_face) continue;
      cloud.positions.push_back(World(y).cast<float>());
      cloud.normals.push_back((rotation_ * n).cast<float>());
    }
    return cloud;
  }

 private:
  static inline const Vec3d kCentre{0.013, -0.021, 0.008};
  double Evaluate(const Vec3d& x, Vec3d* gradient) const {
    const Vec3d y = rotation_.transpose() * (x - kCentre);
    double best = -1e300;
    for (const Vec3d& n : normals_) {
      const double v = n.dot(y) - offset_;
      if (v > best) {
        best = v;
        if (gradient) *gradient = rotation_ * n;
      }
    }
    return best;
  }
  std::vector<Vec3d> normals_;
  double offset_;
  Eigen::Matrix3d rotation_;
};

// A box of half-sizes a, b, c turned off the axes by PlateTurn(), its faces outward: with c small,
// a thin plate.
inline Eigen::Matrix3d PlateTurn() {
  return (Eigen::AngleAxisd(0.54, Vec3d::UnitZ()) * Eigen::AngleAxisd(-0.30, Vec3d::UnitY()) *
          Eigen::AngleAxisd(0.40, Vec3d::UnitX()))
      .toRotationMatrix();
}
inline TriangleMesh TurnedPlate(double a, double b, double c) {
  TriangleMesh plate;
  const Eigen::Matrix3d turn = PlateTurn();
  for (int k = 0; k < 8; ++k) {
    const Vec3d corner((k & 1) ? a : -a, (k & 2) ? b : -b, (k & 4) ? c : -c);
    plate.vertices.push_back((turn * corner).cast<float>());
  }
  plate.faces = {{0, 2, 1}, {1, 2, 3}, {4, 5, 6}, {5, 7, 6}, {0, 1, 4}, {1, 5, 4},
                 {2, 6, 3}, {3, 6, 7}, {0, 4, 2}, {2, 4, 6}, {1, 3, 5}, {3, 7, 5}};
  return plate;
}

inline TurnedPolyhedron Cube() {  // Edge 1.
  return TurnedPolyhedron(
      {Vec3d::UnitX(), -Vec3d::UnitX(), Vec3d::UnitY(), -Vec3d::UnitY(), Vec3d::UnitZ(), -Vec3d::UnitZ()}, 0.5);
}

inline TurnedPolyhedron Octahedron() {  // Corners at distance 0.6 on the axes.
  std::vector<Vec3d> normals;
  for (int s = 0; s < 8; ++s) normals.push_back(Vec3d(s & 1 ? -1 : 1, s & 2 ? -1 : 1, s & 4 ? -1 : 1) / std::sqrt(3.0));
  return TurnedPolyhedron(normals, 0.6 / std::sqrt(3.0));
}

// The outward normals of a pyramid's faces: the base (−z) and one side per azimuth (degrees),
// rising at `elevation_degrees` from the base.
inline std::vector<Vec3d> PyramidNormals(const std::vector<double>& azimuths_degrees, double elevation_degrees) {
  constexpr double kRadians = 3.14159265358979323846 / 180;
  const double e = elevation_degrees * kRadians;
  std::vector<Vec3d> normals{-Vec3d::UnitZ()};
  for (const double degrees : azimuths_degrees) {
    const double a = degrees * kRadians;
    normals.push_back(Vec3d(std::cos(e) * std::cos(a), std::cos(e) * std::sin(a), std::sin(e)));
  }
  return normals;
}

// A pentagonal pyramid's: its sides rise at 40°, so its base edges are 50° sharp.
inline std::vector<Vec3d> PentagonalPyramidNormals() { return PyramidNormals({0, 72, 144, 216, 288}, 40); }

// The largest distance from points along the true edges to the mesh.
inline double EdgeDistance(const TriangleMesh& mesh, const TurnedPolyhedron& shape,
                           const std::vector<std::pair<Vec3d, Vec3d>>& edges) {
  const core::TriangleTree tree(mesh);
  double worst = 0;
  for (const auto& [a, b] : edges) {
    for (int k = 1; k < 20; ++k) {
      worst = std::max(worst, std::sqrt(tree.Closest(shape.World(a + (b - a) * (k / 20.0))).distance2));
    }
  }
  return worst;
}

inline std::vector<std::pair<Vec3d, Vec3d>> CubeEdges() {
  std::vector<std::pair<Vec3d, Vec3d>> edges;
  for (int axis = 0; axis < 3; ++axis) {
    for (int s = 0; s < 4; ++s) {
      Vec3d a, b;
      const int u = (axis + 1) % 3, v = (axis + 2) % 3;
      a[axis] = -0.5, b[axis] = 0.5;
      a[u] = b[u] = s & 1 ? 0.5 : -0.5;
      a[v] = b[v] = s & 2 ? 0.5 : -0.5;
      edges.push_back({a, b});
    }
  }
  return edges;
}

inline std::vector<std::pair<Vec3d, Vec3d>> OctahedronEdges() {
  std::vector<std::pair<Vec3d, Vec3d>> edges;
  for (int a = 0; a < 3; ++a) {
    for (int b = a + 1; b < 3; ++b) {
      for (double sa : {-0.6, 0.6}) {
        for (double sb : {-0.6, 0.6}) {
          Vec3d p = Vec3d::Zero(), q = Vec3d::Zero();
          p[a] = sa, q[b] = sb;
          edges.push_back({p, q});
        }
      }
    }
  }
  return edges;
}

}  // namespace lsqsurf::testing
