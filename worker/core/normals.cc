#include "worker/core/normals.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <limits>
#include <numeric>
#include <queue>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"

namespace lsqsurf::core {

absl::Status Validate(const NormalEstimationParams& params) {
  if (params.neighbors < 3 || params.neighbors > 128) {
    return absl::InvalidArgumentError("normal_neighbors must be between 3 and 128");
  }
  if (params.scales < 1 || params.scales > 4) {
    return absl::InvalidArgumentError("normal estimation scales must be between 1 and 4");
  }
  return absl::OkStatus();
}

namespace {

// The k nearest points of a clean scan lie flatter than this (λ₀ / Σλ; the spread along the
// normal under 8 % of the spread across): larger neighbourhoods are not looked at there, which
// keeps clean clouds at the cost of one small query per point.
constexpr double kFlatEnough = 3e-3;

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

// Looks at the first `from_size`, 2 × `from_size` − 1, … points of the neighbourhood (closest
// first, the point itself among them; all of them last) and keeps in `normal` and `variation`
// the least-variance direction of the flattest, where it is flatter than `variation` already is
// (ties keep the smaller). The sums run once over the points, about `centre` for precision.
void KeepFlattest(std::span<const Vec3f> points, const Vec3f& centre, const std::vector<Neighbor>& neighbourhood,
                  size_t from_size, Vec3f& normal, double& variation) {
  Vec3d sum = Vec3d::Zero();
  Eigen::Matrix3d outer = Eigen::Matrix3d::Zero();
  size_t next_size = std::min(from_size, neighbourhood.size());
  for (size_t q = 0; q < neighbourhood.size(); ++q) {
    const Vec3d d = (points[neighbourhood[q].index] - centre).cast<double>();
    sum += d;
    outer += d * d.transpose();
    if (q + 1 != next_size) continue;
    const double count = static_cast<double>(q + 1);
    const Eigen::Matrix3d covariance = outer / count - (sum / count) * (sum / count).transpose();
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
    eig.computeDirect(covariance);
    const double total = eig.eigenvalues().sum();
    const double flatness = total > 0 ? eig.eigenvalues()(0) / total : 0.0;
    if (flatness < variation) {
      variation = flatness;
      normal = eig.eigenvectors().col(0).cast<float>().normalized();
    }
    next_size = std::min(2 * (next_size - 1) + 1, neighbourhood.size());
  }
}

}  // namespace

absl::StatusOr<std::vector<Vec3f>> EstimateNormals(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                                   JobContext& ctx) {
  if (absl::Status s = Validate(params); !s.ok()) return s;
  const size_t n = points.size();
  if (n < 3) return absl::InvalidArgumentError("normal estimation needs at least 3 points");
  const size_t k = std::min<size_t>(static_cast<size_t>(params.neighbors), n - 1);
  const size_t largest = std::min<size_t>(k << (params.scales - 1), n - 1);

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
          double variation = std::numeric_limits<double>::infinity();
          normals[i] = Vec3f::UnitZ();
          KeepFlattest(points, points[i], nn, k + 1, normals[i], variation);
          if (largest > k && variation > kFlatEnough) {
            tree.Knn(points[i], largest + 1, nn);
            KeepFlattest(points, points[i], nn, 2 * k + 1, normals[i], variation);
          }
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
