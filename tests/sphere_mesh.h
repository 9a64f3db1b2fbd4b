// tests/sphere_mesh.h — a triangulated sphere with exact normals, shared by the renderer's tests
// and its benchmark (no test framework needed).
#pragma once

#include <cmath>
#include <numbers>

#include "worker/core/geometry.h"

namespace lsqsurf::testing {

// Latitude–longitude sphere mesh of radius `radius` at the origin, outward faces, exact vertex
// normals and a "height" attribute equal to z.
inline core::TriangleMesh SphereMesh(int rings, int segments, double radius = 1.0) {
  core::TriangleMesh mesh;
  core::ScalarAttribute height{"height", {}};
  for (int i = 0; i <= rings; ++i) {
    const double theta = std::numbers::pi * i / rings;
    for (int j = 0; j < segments; ++j) {
      const double phi = 2 * std::numbers::pi * j / segments;
      const core::Vec3d d(std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi), std::cos(theta));
      mesh.vertices.push_back((radius * d).cast<float>());
      mesh.normals.push_back(d.cast<float>());
      height.values.push_back(static_cast<float>(radius * d.z()));
    }
  }
  auto at = [&](int i, int j) { return static_cast<uint32_t>(i * segments + (j % segments)); };
  for (int i = 0; i < rings; ++i) {
    for (int j = 0; j < segments; ++j) {
      if (i > 0) mesh.faces.push_back({at(i, j), at(i + 1, j), at(i, j + 1)});
      if (i + 1 < rings) mesh.faces.push_back({at(i, j + 1), at(i + 1, j), at(i + 1, j + 1)});
    }
  }
  mesh.vertex_attributes.push_back(std::move(height));
  return mesh;
}

}  // namespace lsqsurf::testing
