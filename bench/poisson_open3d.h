// bench/poisson_open3d.h — screened Poisson reconstruction (Open3D's implementation of Kazhdan &
// Hoppe), the reference the benchmark compares against in the same run.
#pragma once

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::bench {

struct PoissonOptions {
  int depth = 10;                    // Octree depth; 10 is the reference setting of BENCHMARKS.md.
  double scale = 1.1;                // Reconstruction cube / bounding cube of the points.
  double trim_density_quantile = 0;  // Drop the vertices below this density quantile (0 = keep all,
                                     // as the plain watertight Poisson surface).
};

// Needs oriented normals. Errors: kInvalidArgument, kInternal (Open3D produced nothing).
absl::StatusOr<core::TriangleMesh> ScreenedPoisson(const core::PointCloud& cloud, const PoissonOptions& options);

}  // namespace lsqsurf::bench
