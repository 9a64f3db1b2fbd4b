#include "bench/poisson_open3d.h"

#include <open3d/geometry/PointCloud.h>
#include <open3d/geometry/TriangleMesh.h>

#include <algorithm>

namespace lsqsurf::bench {

absl::StatusOr<core::TriangleMesh> ScreenedPoisson(const core::PointCloud& cloud, const PoissonOptions& options) {
  if (!cloud.has_normals()) return absl::InvalidArgumentError("screened Poisson needs oriented normals");
  if (options.depth < 1 || options.depth > 16) return absl::InvalidArgumentError("Poisson depth must be in [1, 16]");
  open3d::geometry::PointCloud points;
  points.points_.reserve(cloud.size());
  points.normals_.reserve(cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    points.points_.push_back(cloud.positions[i].cast<double>());
    points.normals_.push_back(cloud.normals[i].cast<double>());
  }
  auto [mesh, densities] = open3d::geometry::TriangleMesh::CreateFromPointCloudPoisson(
      points, static_cast<size_t>(options.depth), 0.0f, static_cast<float>(options.scale), false);
  if (!mesh || mesh->triangles_.empty()) return absl::InternalError("Open3D's Poisson produced no surface");
  if (options.trim_density_quantile > 0) {
    std::vector<double> sorted = densities;
    const auto k = static_cast<std::ptrdiff_t>(options.trim_density_quantile * static_cast<double>(sorted.size()));
    std::nth_element(sorted.begin(), sorted.begin() + k, sorted.end());
    const double cut = sorted[static_cast<size_t>(k)];
    std::vector<bool> drop(densities.size());
    for (size_t i = 0; i < densities.size(); ++i) drop[i] = densities[i] < cut;
    mesh->RemoveVerticesByMask(drop);
  }
  core::TriangleMesh out;
  out.vertices.reserve(mesh->vertices_.size());
  for (const auto& v : mesh->vertices_) out.vertices.push_back(v.cast<float>());
  out.faces.reserve(mesh->triangles_.size());
  for (const auto& t : mesh->triangles_) {
    out.faces.push_back({static_cast<uint32_t>(t[0]), static_cast<uint32_t>(t[1]), static_cast<uint32_t>(t[2])});
  }
  return out;
}

}  // namespace lsqsurf::bench
