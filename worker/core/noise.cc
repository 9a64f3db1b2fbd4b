#include "worker/core/noise.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <vector>

#include "worker/core/parallel.h"

namespace lsqsurf::core {
namespace {

constexpr size_t kSamples = 2048;
constexpr size_t kNeighbors = 48;
constexpr size_t kMaxFitPoints = 256;
constexpr double kBallFactor = 4.0;
constexpr int kQuadricTerms = 6;

double Median(std::vector<double>& values) {
  auto middle = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
  std::nth_element(values.begin(), middle, values.end());
  return *middle;
}

// Neighbours whose normals turn more than 60° from the point's own lie on another sheet (the far
// side of a plate thinner than the neighbourhood, the other face of a crease): not noise.
constexpr float kSameSheetCos = 0.5f;

// Residual RMS of the least-squares height w = quadratic(u, v) over the neighbourhood `near` of
// p (normal `own`) on p's own sheet, in the frame of their mean normal (u, v scaled by the
// neighbourhood's radius so that the 6×6 system stays well conditioned); -1 where there is no
// frame or too few points.
double QuadricResidual(const KdTree& tree, std::span<const Vec3f> normals, const Vec3f& p, const Vec3f& own,
                       std::vector<Neighbor>& near) {
  const std::span<const Vec3f> points = tree.points();
  std::erase_if(near, [&](const Neighbor& q) { return normals[q.index].dot(own) < kSameSheetCos; });
  const size_t step = std::max<size_t>(1, near.size() / kMaxFitPoints);
  Vec3d normal = Vec3d::Zero();
  double radius2 = 0;
  for (size_t j = 0; j < near.size(); j += step) {
    normal += normals[near[j].index].cast<double>();
    radius2 = std::max(radius2, static_cast<double>(near[j].distance2));
  }
  const double radius = std::sqrt(radius2);
  if (!(normal.norm() > 0) || !(radius > 0)) return -1;
  normal.normalize();
  const Vec3d tu = normal.unitOrthogonal(), tv = normal.cross(tu);
  Eigen::Matrix<double, kQuadricTerms, kQuadricTerms> ata = Eigen::Matrix<double, kQuadricTerms, kQuadricTerms>::Zero();
  Eigen::Matrix<double, kQuadricTerms, 1> atw = Eigen::Matrix<double, kQuadricTerms, 1>::Zero();
  std::vector<Eigen::Matrix<double, kQuadricTerms + 1, 1>> rows;
  for (size_t j = 0; j < near.size(); j += step) {
    const Vec3d d = (points[near[j].index] - p).cast<double>();
    const double u = tu.dot(d) / radius, v = tv.dot(d) / radius, w = normal.dot(d);
    Eigen::Matrix<double, kQuadricTerms + 1, 1> row;
    row << 1, u, v, u * u, u * v, v * v, w;
    ata.selfadjointView<Eigen::Lower>().rankUpdate(row.head<kQuadricTerms>());
    atw += w * row.head<kQuadricTerms>();
    rows.push_back(row);
  }
  if (rows.size() <= static_cast<size_t>(kQuadricTerms)) return -1;
  const Eigen::Matrix<double, kQuadricTerms, kQuadricTerms> full = ata.selfadjointView<Eigen::Lower>();
  const Eigen::LDLT<Eigen::Matrix<double, kQuadricTerms, kQuadricTerms>> solver(full);
  if (solver.info() != Eigen::Success) return -1;
  const Eigen::Matrix<double, kQuadricTerms, 1> c = solver.solve(atw);
  double energy = 0;
  for (const auto& row : rows) {
    const double r = row(kQuadricTerms) - row.head<kQuadricTerms>().dot(c);
    energy += r * r;
  }
  return std::sqrt(energy / static_cast<double>(rows.size() - kQuadricTerms));
}

}  // namespace

NoiseEstimate EstimateNoise(const KdTree& tree, std::span<const Vec3f> normals, double known_sigma) {
  NoiseEstimate estimate;
  if (known_sigma >= 0) estimate.sigma = known_sigma;
  const std::span<const Vec3f> points = tree.points();
  const size_t n = points.size();
  if (n < kNeighbors) return estimate;
  const size_t stride = std::max<size_t>(1, n / kSamples);
  const size_t samples = (n + stride - 1) / stride;
  for (int pass = 0; pass < 4; ++pass) {
    const double ball = kBallFactor * estimate.sigma;
    std::vector<double> rms(samples, 0.0), counts(samples, 0.0);
    (void)ParallelFor(samples, 32, [&](size_t begin, size_t end) {
      std::vector<Neighbor> near;
      for (size_t i = begin; i < end; ++i) {
        const Vec3f& p = points[i * stride];
        tree.Knn(p, kNeighbors, near);
        if (ball * ball > near.back().distance2) tree.Radius(p, static_cast<float>(ball), near);
        counts[i] = static_cast<double>(near.size());
        if (known_sigma >= 0) continue;
        rms[i] = std::max(0.0, QuadricResidual(tree, normals, p, normals[i * stride], near));
      }
    });
    estimate.points_in_ball = Median(counts);
    if (known_sigma >= 0) break;
    const double sigma = Median(rms);
    const bool settled = sigma <= 1.1 * estimate.sigma;
    estimate.sigma = std::max(estimate.sigma, sigma);
    if (settled) break;  // The ball counted was within 10% of the final one.
  }
  return estimate;
}

}  // namespace lsqsurf::core
