#include "worker/core/normals.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <numeric>
#include <queue>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"

namespace lsqsurf::core {

absl::Status Validate(const NormalEstimationParams& params) {
  if (params.neighbors < 3 || params.neighbors > 128) {
    return absl::InvalidArgumentError("normal_neighbors must be between 3 and 128");
  }
  return absl::OkStatus();
}

namespace {

// Outward per component: the sign that makes the normals point away from its centroid.
void PointAwayFromCentroids(std::span<const Vec3f> points, const std::vector<uint32_t>& component, uint32_t components,
                            std::vector<Vec3f>& normals) {
  const size_t n = points.size();
  std::vector<Vec3d> centroid(components, Vec3d::Zero());
  std::vector<double> count(components, 0.0), flux(components, 0.0);
  for (size_t i = 0; i < n; ++i) {
    centroid[component[i]] += points[i].cast<double>();
    count[component[i]] += 1.0;
  }
  for (uint32_t c = 0; c < components; ++c) centroid[c] /= count[c];
  for (size_t i = 0; i < n; ++i) {
    flux[component[i]] += (points[i].cast<double>() - centroid[component[i]]).dot(normals[i].cast<double>());
  }
  for (size_t i = 0; i < n; ++i) {
    if (flux[component[i]] < 0) normals[i] = -normals[i];
  }
}

}  // namespace

absl::StatusOr<std::vector<Vec3f>> EstimateNormals(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                                   JobContext& ctx) {
  if (absl::Status s = Validate(params); !s.ok()) return s;
  const size_t n = points.size();
  if (n < 3) return absl::InvalidArgumentError("normal estimation needs at least 3 points");
  const size_t k = std::min<size_t>(static_cast<size_t>(params.neighbors), n - 1);

  SubContext pca_ctx(ctx, "estimating normals", 0.0, 0.6);
  KdTree tree(points);
  std::vector<uint32_t> knn(n * k);
  std::vector<Vec3f> normals(n);
  absl::Status status = ParallelFor(
      n, 1024,
      [&](size_t begin, size_t end) {
        std::vector<Neighbor> nn;
        for (size_t i = begin; i < end; ++i) {
          tree.Knn(points[i], k + 1, nn);
          Vec3d mean = Vec3d::Zero();
          for (const Neighbor& q : nn) mean += points[q.index].cast<double>();
          mean /= static_cast<double>(nn.size());
          Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
          for (const Neighbor& q : nn) {
            const Vec3d d = points[q.index].cast<double>() - mean;
            cov += d * d.transpose();
          }
          Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
          eig.computeDirect(cov);
          normals[i] = eig.eigenvectors().col(0).cast<float>().normalized();
          // Skip the query point itself (normally first); keep exactly k graph neighbours.
          size_t written = 0;
          for (const Neighbor& q : nn) {
            if (q.index == i || written == k) continue;
            knn[i * k + written++] = q.index;
          }
          while (written < k) knn[i * k + written++] = static_cast<uint32_t>(i);
        }
      },
      &ctx, [&](double f) { pca_ctx.Report(f); });
  if (!status.ok()) return status;

  // Symmetric adjacency (CSR) of the k-NN graph: orientation must be able to cross an edge
  // from either end.
  SubContext orient_ctx(ctx, "orienting normals", 0.6, 1.0);
  std::vector<uint32_t> degree(n + 1, 0);
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < k; ++j) {
      ++degree[i];
      ++degree[knn[i * k + j]];
    }
  std::vector<uint64_t> offset(n + 1, 0);
  for (size_t i = 0; i < n; ++i) offset[i + 1] = offset[i] + degree[i];
  std::vector<uint32_t> adjacency(offset[n]);
  std::vector<uint64_t> cursor(offset.begin(), offset.end() - 1);
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < k; ++j) {
      const uint32_t other = knn[i * k + j];
      adjacency[cursor[i]++] = other;
      adjacency[cursor[other]++] = static_cast<uint32_t>(i);
    }
  knn.clear();
  knn.shrink_to_fit();

  // Prim's algorithm, one tree per connected component, seeded at the highest point whose
  // normal is turned towards +z (Hoppe's choice).
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return points[a].z() > points[b].z(); });
  std::vector<uint32_t> component(n, UINT32_MAX);
  struct Edge {
    float cost;
    uint32_t from, to;
    bool operator>(const Edge& o) const { return cost > o.cost; }
  };
  std::priority_queue<Edge, std::vector<Edge>, std::greater<>> heap;
  uint32_t components = 0;
  size_t visited = 0;
  for (uint32_t seed : order) {
    if (component[seed] != UINT32_MAX) continue;
    if (normals[seed].z() < 0) normals[seed] = -normals[seed];
    const uint32_t c = components++;
    component[seed] = c;
    auto push_edges = [&](uint32_t from) {
      for (uint64_t e = offset[from]; e < offset[from + 1]; ++e) {
        const uint32_t to = adjacency[e];
        if (component[to] != UINT32_MAX) continue;
        heap.push({1.0f - std::abs(normals[from].dot(normals[to])), from, to});
      }
    };
    push_edges(seed);
    while (!heap.empty()) {
      const Edge edge = heap.top();
      heap.pop();
      if (component[edge.to] != UINT32_MAX) continue;
      component[edge.to] = c;
      if (normals[edge.from].dot(normals[edge.to]) < 0) normals[edge.to] = -normals[edge.to];
      push_edges(edge.to);
      if ((++visited & 0xFFFF) == 0) {
        if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
        orient_ctx.Report(static_cast<double>(visited) / static_cast<double>(n));
      }
    }
  }

  PointAwayFromCentroids(points, component, components, normals);
  orient_ctx.Report(1.0);
  return normals;
}

}  // namespace lsqsurf::core
