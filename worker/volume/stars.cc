#include "worker/volume/stars.h"

#include <Eigen/Dense>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <numbers>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::volume {
namespace {

using Mat3 = Eigen::Matrix3d;

// A system whose smallest eigenvalue is below this share of its largest is treated as singular
// (the star is flat or a line to within ~1 %).
constexpr double kSingularRatio = 1e-4;

Sym3 ToSym(const Mat3& m) {
  return {static_cast<float>(m(0, 0)), static_cast<float>(m(1, 1)), static_cast<float>(m(2, 2)),
          static_cast<float>(m(0, 1)), static_cast<float>(m(0, 2)), static_cast<float>(m(1, 2))};
}

// M = det(C)^{1/3} C⁻¹, from C's axis lengths √λ: ratios up to 2:1 count as none (the stars of
// structured tetrahedrisations, such as Kuhn's six tetrahedra per cube, are 2:1 along the cut
// diagonal although the vertices sample space evenly), larger ones are reduced by that factor
// and capped at `max_anisotropy`; an isotropic identity for a star with no extent.
Mat3 UnitMetric(const Mat3& c, double max_anisotropy) {
  Eigen::SelfAdjointEigenSolver<Mat3> eig(c);
  const Eigen::Vector3d l = eig.eigenvalues();
  if (!(l.maxCoeff() > 0)) return Mat3::Identity();
  Eigen::Vector3d log_length;
  for (int a = 0; a < 3; ++a) log_length[a] = 0.5 * std::log(std::max(l[a], l.maxCoeff() * 1e-12));
  log_length.array() -= log_length.mean();
  const double spread = log_length.maxCoeff() - log_length.minCoeff();
  const double kept = std::min(std::max(0.0, spread - std::log(2.0)), std::log(max_anisotropy));
  if (kept <= 0) return Mat3::Identity();
  log_length *= kept / spread;
  log_length.array() -= log_length.mean();  // Unit determinant.
  const Eigen::Vector3d inverse_length2 = (-2.0 * log_length).array().exp();
  return eig.eigenvectors() * inverse_length2.asDiagonal() * eig.eigenvectors().transpose();
}

struct StarWork {
  std::vector<uint32_t> members;
  std::vector<uint32_t> wider;
};

// Weighted normal matrix of the star; returns the ratio of its extreme eigenvalues.
double NormalMatrix(const VolumeMesh& mesh, size_t i, std::span<const uint32_t> star, GradientWeights kind, double h2,
                    Mat3& a) {
  const Vec3d xi = mesh.positions[i].cast<double>();
  a.setZero();
  for (uint32_t k : star) {
    const Vec3d d = mesh.positions[k].cast<double>() - xi;
    const double d2 = d.squaredNorm();
    if (d2 == 0) continue;
    const double w = kind == GradientWeights::kGaussian ? std::exp(-d2 / h2) : 1.0 / d2;
    a += w * d * d.transpose();
  }
  Eigen::SelfAdjointEigenSolver<Mat3> eig(a, Eigen::EigenvaluesOnly);
  const double largest = eig.eigenvalues().maxCoeff();
  return largest > 0 ? eig.eigenvalues().minCoeff() / largest : 0.0;
}

}  // namespace

Adjacency BuildAdjacency(const VolumeMesh& mesh, int k) {
  const size_t n = mesh.vertex_count();
  Adjacency adj;
  adj.start.assign(n + 1, 0);
  if (!mesh.has_cells()) {
    core::KdTree tree(mesh.positions);
    const size_t kk = std::min<size_t>(static_cast<size_t>(k), n - 1);
    adj.neighbor.resize(n * kk);
    (void)core::ParallelFor(n, 2048, [&](size_t begin, size_t end) {
      std::vector<core::Neighbor> nn;
      for (size_t i = begin; i < end; ++i) {
        tree.Knn(mesh.positions[i], kk + 1, nn);
        size_t out = 0;
        for (const core::Neighbor& q : nn) {
          if (q.index != i && out < kk) adj.neighbor[i * kk + out++] = q.index;
        }
        // Coincident points can push i itself past the k-th place; repeat the last one then.
        for (; out < kk; ++out) adj.neighbor[i * kk + out] = adj.neighbor[i * kk + out - 1];
      }
    });
    for (size_t i = 0; i <= n; ++i) adj.start[i] = i * kk;
    return adj;
  }
  // Vertex → cells incidence, then each vertex's star as the sorted union of its cells' vertices.
  std::vector<uint64_t> cell_start(n + 1, 0);
  for (uint32_t v : mesh.cell_vertices) ++cell_start[v + 1];
  for (size_t i = 0; i < n; ++i) cell_start[i + 1] += cell_start[i];
  std::vector<uint32_t> cells(cell_start[n]);
  {
    std::vector<uint64_t> cursor(cell_start.begin(), cell_start.end() - 1);
    for (size_t c = 0; c < mesh.cell_count(); ++c) {
      for (uint32_t v : mesh.cell(c)) cells[cursor[v]++] = static_cast<uint32_t>(c);
    }
  }
  // A sliver or collapsed cell joins vertices across it that no usable cell joins (a Delaunay
  // hull sliver spans four hull points): it adds to a star only a vertex that has nothing else.
  std::vector<char> flat(mesh.cell_count());
  (void)core::ParallelFor(mesh.cell_count(), 4096, [&](size_t begin, size_t end) {
    for (size_t c = begin; c < end; ++c) flat[c] = core::MeasureCell(mesh, c).degenerate();
  });
  std::vector<std::vector<uint32_t>> stars(n);
  (void)core::ParallelFor(n, 2048, [&](size_t begin, size_t end) {
    for (size_t i = begin; i < end; ++i) {
      auto& s = stars[i];
      for (const bool take_flat : {false, true}) {
        for (uint64_t e = cell_start[i]; e < cell_start[i + 1]; ++e) {
          if (flat[cells[e]] != take_flat) continue;
          for (uint32_t v : mesh.cell(cells[e])) {
            if (v != i) s.push_back(v);
          }
        }
        if (!s.empty()) break;
      }
      std::sort(s.begin(), s.end());
      s.erase(std::unique(s.begin(), s.end()), s.end());
    }
  });
  for (size_t i = 0; i < n; ++i) adj.start[i + 1] = adj.start[i] + stars[i].size();
  adj.neighbor.resize(adj.start[n]);
  for (size_t i = 0; i < n; ++i) {
    std::copy(stars[i].begin(), stars[i].end(), adj.neighbor.begin() + static_cast<int64_t>(adj.start[i]));
    std::vector<uint32_t>().swap(stars[i]);
  }
  return adj;
}

absl::StatusOr<VertexStars> AnalyseStars(const VolumeMesh& mesh, std::span<const VertexField* const> fields,
                                         const StarParams& params, core::JobContext& ctx) {
  const size_t n = mesh.vertex_count();
  if (n < 5) return absl::InvalidArgumentError("a volume needs at least 5 vertices");
  const Adjacency adj = BuildAdjacency(mesh, params.neighbors);
  VertexStars out;
  out.gradients.assign(fields.size(), std::vector<Vec3f>(n, Vec3f::Zero()));
  out.metric.resize(n);
  out.volume.assign(n, 0.0f);
  out.mean_edge.resize(n);
  out.mean_star_size = static_cast<double>(adj.neighbor.size()) / static_cast<double>(n);
  if (mesh.has_cells()) {
    const auto tets = Tetrahedralize(mesh);
    // Each tetrahedron's volume is shared by its 4 corners: the same total as cell / vertices for
    // a simplex and close to it for the other cells, without per-type rules.
    for (const auto& t : tets) {
      const double v =
          TetVolume(mesh.positions[t[0]], mesh.positions[t[1]], mesh.positions[t[2]], mesh.positions[t[3]]);
      for (uint32_t k : t) out.volume[k] += static_cast<float>(v / 4.0);
    }
  }
  std::atomic<int64_t> widened{0}, singular{0};
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 1024,
      [&](size_t begin, size_t end) {
        StarWork work;
        for (size_t i = begin; i < end; ++i) {
          const Vec3d xi = mesh.positions[i].cast<double>();
          std::span<const uint32_t> star = adj.of(i);
          double edge = 0, farthest2 = 0;
          Mat3 cov = Mat3::Zero();
          for (uint32_t k : star) {
            const Vec3d d = mesh.positions[k].cast<double>() - xi;
            edge += d.norm();
            farthest2 = std::max(farthest2, d.squaredNorm());
            cov += d * d.transpose();
          }
          edge /= static_cast<double>(std::max<size_t>(1, star.size()));
          out.mean_edge[i] = static_cast<float>(edge);
          out.metric[i] =
              ToSym(UnitMetric(cov / static_cast<double>(std::max<size_t>(1, star.size())), params.max_anisotropy));
          if (!mesh.has_cells()) {
            out.volume[i] = static_cast<float>(4.0 / 3.0 * std::numbers::pi * std::pow(farthest2, 1.5) /
                                               static_cast<double>(star.size() + 1));
          }
          if (fields.empty() || edge == 0) continue;
          const double h2 = edge * edge;
          Mat3 a;
          double ratio = NormalMatrix(mesh, i, star, params.weights, h2, a);
          if (ratio < kSingularRatio) {
            // The two-ring: the star's stars.
            work.wider.assign(star.begin(), star.end());
            for (uint32_t k : star) {
              for (uint32_t m : adj.of(k)) {
                if (m != i) work.wider.push_back(m);
              }
            }
            std::sort(work.wider.begin(), work.wider.end());
            work.wider.erase(std::unique(work.wider.begin(), work.wider.end()), work.wider.end());
            star = work.wider;
            ratio = NormalMatrix(mesh, i, star, params.weights, h2, a);
            widened.fetch_add(1, std::memory_order_relaxed);
          }
          Eigen::SelfAdjointEigenSolver<Mat3> eig(a);
          Eigen::Vector3d inv = Eigen::Vector3d::Zero();
          const double largest = eig.eigenvalues().maxCoeff();
          for (int c = 0; c < 3; ++c) {
            if (eig.eigenvalues()[c] > kSingularRatio * largest) inv[c] = 1.0 / eig.eigenvalues()[c];
          }
          if (ratio < kSingularRatio) singular.fetch_add(1, std::memory_order_relaxed);
          const Mat3 pinv = eig.eigenvectors() * inv.asDiagonal() * eig.eigenvectors().transpose();
          for (size_t f = 0; f < fields.size(); ++f) {
            const float fi = fields[f]->values[i];
            Vec3d b = Vec3d::Zero();
            for (uint32_t k : star) {
              const Vec3d d = mesh.positions[k].cast<double>() - xi;
              const double d2 = d.squaredNorm();
              if (d2 == 0) continue;
              const double w = params.weights == GradientWeights::kGaussian ? std::exp(-d2 / h2) : 1.0 / d2;
              b += w * (fields[f]->values[k] - fi) * d;
            }
            out.gradients[f][i] = (pinv * b).cast<float>();
          }
        }
      },
      &ctx));
  out.widened_stars = widened.load();
  out.singular_stars = singular.load();
  double total_edge = 0;
  for (float e : out.mean_edge) total_edge += e;
  if (!(total_edge > 0)) return absl::InvalidArgumentError("all vertices of the volume coincide");
  return out;
}

}  // namespace lsqsurf::volume
