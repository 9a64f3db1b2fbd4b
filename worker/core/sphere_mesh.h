// worker/core/sphere_mesh.h — a triangulated sphere with exact normals: a reference shape for
// the renderer's tests, its benchmark and the fuzzers' seeds.
#pragma once

#include <cmath>
#include <numbers>

#include "worker/core/geometry.h"

namespace lsqsurf::core {

// Latitude–longitude sphere mesh of radius `radius` at the origin: one vertex per pole, so the
// mesh is closed and edge-manifold, faces wound counter-clockwise seen from outside, exact
// vertex normals and a "height" attribute equal to z. 2·segments·(rings − 1) triangles.
inline TriangleMesh SphereMesh(int rings, int segments, double radius = 1.0) {
  TriangleMesh mesh;
  ScalarAttribute height{"height", {}};
  auto add_vertex = [&](double theta, double phi) {
    const Vec3d d(std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi), std::cos(theta));
    mesh.vertices.push_back((radius * d).cast<float>());
    mesh.normals.push_back(d.cast<float>());
    height.values.push_back(static_cast<float>(radius * d.z()));
  };
  add_vertex(0, 0);  // North pole: vertex 0.
  for (int i = 1; i < rings; ++i) {
    for (int j = 0; j < segments; ++j) add_vertex(std::numbers::pi * i / rings, 2 * std::numbers::pi * j / segments);
  }
  add_vertex(std::numbers::pi, 0);  // South pole: the last vertex.
  const auto south = static_cast<uint32_t>(mesh.vertices.size() - 1);
  // Ring i (1..rings−1), segment j (wrapping).
  auto at = [&](int i, int j) { return static_cast<uint32_t>(1 + (i - 1) * segments + (j % segments)); };
  for (int j = 0; j < segments; ++j) {
    mesh.faces.push_back({0, at(1, j), at(1, j + 1)});
    mesh.faces.push_back({south, at(rings - 1, j + 1), at(rings - 1, j)});
  }
  for (int i = 1; i + 1 < rings; ++i) {
    for (int j = 0; j < segments; ++j) {
      mesh.faces.push_back({at(i, j), at(i + 1, j), at(i, j + 1)});
      mesh.faces.push_back({at(i, j + 1), at(i + 1, j), at(i + 1, j + 1)});
    }
  }
  mesh.vertex_attributes.push_back(std::move(height));
  return mesh;
}

}  // namespace lsqsurf::core
