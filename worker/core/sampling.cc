#include "worker/core/sampling.h"

#include <algorithm>
#include <random>

namespace lsqsurf::core {

std::vector<Vec3f> VertexNormals(const TriangleMesh& mesh) {
  std::vector<Vec3d> sum(mesh.vertices.size(), Vec3d::Zero());
  for (const Triangle& f : mesh.faces) {
    const Vec3d a = mesh.vertices[f[0]].cast<double>();
    // Unnormalised cross product = 2 × area × unit normal: area weighting for free.
    const Vec3d n = (mesh.vertices[f[1]].cast<double>() - a).cross(mesh.vertices[f[2]].cast<double>() - a);
    for (uint32_t v : f) sum[v] += n;
  }
  std::vector<Vec3f> out(sum.size());
  for (size_t i = 0; i < sum.size(); ++i) {
    const double len = sum[i].norm();
    out[i] = len > 0 ? Vec3f((sum[i] / len).cast<float>()) : Vec3f::UnitZ();
  }
  return out;
}

std::vector<SurfaceSample> SampleSurface(const TriangleMesh& mesh, size_t count, uint64_t seed, bool smooth_normals) {
  std::vector<SurfaceSample> out;
  if (mesh.faces.empty() || count == 0) return out;
  std::vector<double> cumulative(mesh.faces.size());
  double total = 0;
  for (size_t i = 0; i < mesh.faces.size(); ++i) {
    const auto& f = mesh.faces[i];
    const Vec3d a = mesh.vertices[f[0]].cast<double>();
    total += 0.5 * (mesh.vertices[f[1]].cast<double>() - a).cross(mesh.vertices[f[2]].cast<double>() - a).norm();
    cumulative[i] = total;
  }
  std::vector<Vec3f> vertex_normals;
  if (smooth_normals) {
    vertex_normals = mesh.normals.size() == mesh.vertices.size() ? mesh.normals : VertexNormals(mesh);
  }
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  out.reserve(count);
  for (size_t s = 0; s < count; ++s) {
    const double pick = uniform(rng) * total;
    const size_t fi = std::min<size_t>(
        std::upper_bound(cumulative.begin(), cumulative.end(), pick) - cumulative.begin(), mesh.faces.size() - 1);
    const auto& f = mesh.faces[fi];
    // Square-root warping gives uniform barycentric coordinates over the triangle.
    const double r1 = std::sqrt(uniform(rng)), r2 = uniform(rng);
    const double wa = 1 - r1, wb = r1 * (1 - r2), wc = r1 * r2;
    const Vec3d a = mesh.vertices[f[0]].cast<double>(), b = mesh.vertices[f[1]].cast<double>(),
                c = mesh.vertices[f[2]].cast<double>();
    Vec3d n;
    if (smooth_normals) {
      n = wa * vertex_normals[f[0]].cast<double>() + wb * vertex_normals[f[1]].cast<double>() +
          wc * vertex_normals[f[2]].cast<double>();
    } else {
      n = (b - a).cross(c - a);
    }
    if (n.norm() == 0) n = (b - a).cross(c - a);
    if (n.norm() == 0) n = Vec3d::UnitZ();
    out.push_back({Vec3f((wa * a + wb * b + wc * c).cast<float>()), Vec3f(n.normalized().cast<float>()),
                   static_cast<uint32_t>(fi)});
  }
  return out;
}

PointCloud SampleCloud(const TriangleMesh& mesh, size_t count, uint64_t seed, double noise_sigma, bool smooth_normals) {
  PointCloud cloud;
  const auto samples = SampleSurface(mesh, count, seed, smooth_normals);
  cloud.positions.reserve(samples.size());
  cloud.normals.reserve(samples.size());
  std::mt19937_64 rng(seed ^ 0x9e3779b97f4a7c15ull);
  std::normal_distribution<double> noise(0.0, noise_sigma > 0 ? noise_sigma : 1.0);
  for (const auto& s : samples) {
    Vec3f p = s.position;
    if (noise_sigma > 0) p += static_cast<float>(noise(rng)) * s.normal;
    cloud.positions.push_back(p);
    cloud.normals.push_back(s.normal);
  }
  return cloud;
}

}  // namespace lsqsurf::core
