// worker/core/sampling.h — area-uniform point samples of triangle meshes.
#pragma once

#include <cstdint>
#include <vector>

#include "worker/core/geometry.h"

namespace lsqsurf::core {

struct SurfaceSample {
  Vec3f position;
  Vec3f normal;   // Interpolated vertex normal (smooth), or the face normal if none.
  uint32_t face;  // Face the sample lies on.
};

// Area-weighted vertex normals (outward for outward-oriented faces).
std::vector<Vec3f> VertexNormals(const TriangleMesh& mesh);

// `count` samples uniformly distributed by area; reproducible for a given `seed`.
// With `smooth_normals`, normals are interpolated from vertex normals (computed from the faces
// when the mesh has none); otherwise they are face normals.
std::vector<SurfaceSample> SampleSurface(const TriangleMesh& mesh, size_t count, uint64_t seed,
                                         bool smooth_normals = true);

// A point cloud with normals made from `SampleSurface`; with `noise_sigma` > 0 every point is
// displaced along its normal by Gaussian noise of that standard deviation (model units).
// `smooth_normals` as for SampleSurface: false gives a CAD model's exact face normals.
PointCloud SampleCloud(const TriangleMesh& mesh, size_t count, uint64_t seed, double noise_sigma = 0.0,
                       bool smooth_normals = true);

}  // namespace lsqsurf::core
