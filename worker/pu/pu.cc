#include "worker/pu/pu.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>
#include <optional>
#include <type_traits>

#include "worker/core/binary.h"
#include "worker/core/kd_tree.h"
#include "worker/core/noise.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/j1a.h"
#include "worker/extract/j1a_isosurface.h"
#include "worker/extract/marching_tets.h"
#include "worker/extract/stitch.h"
#include "worker/pu/orthogonal_fit.h"
#include "worker/pu/sharp_fit.h"

namespace lsqsurf::pu {
namespace {

using core::Vec3d;
using core::Vec3f;

constexpr double kSqrt3 = 1.7320508075688772;
// Cells holding more points are split without trying a fit: at any useful threshold a fit over
// thousands of points fails, and gathering them is the expensive part at coarse levels.
constexpr uint32_t kMaxPointsToFit = 1024;
// The fitting ball of a sparse cell grows to at most this multiple of its support radius.
constexpr double kMaxRadiusGrowth = 4.0;
// Share of support points whose normal may oppose the fitted gradient.
constexpr double kMaxInvertedShare = 0.1;
// The local spacing of a point, for the coverage test: the distance to its 8th neighbour (about
// two sample spacings on a surface, robust to pairs of nearly coincident points).
constexpr size_t kSpacingNeighbors = 8;
// Fits over larger balls (coarse cells) are made on an even subsample of this many points; the
// error test still runs over every point, so an accepted fit meets the bound on all of them.
// At worst a cell whose full fit would have passed is split.
constexpr size_t kMaxFitSamples = 256;
// Noisy data (σ above the error threshold): the error bound in units of σ, and the fewest points
// a fit may use (a fit over N points with T terms carries about σ√(T/N) of noise into F).
constexpr double kNoiseBoundFactor = 3.0;
constexpr int kNoisyMinPoints = 80;
// A quadric label in FitLabel::degree.
constexpr int kQuadricLabel = 5;

struct LocalFit {
  Vec3d centre = Vec3d::Zero();  // Of the leaf.
  double support_radius = 0;     // R_i of the PU weight.
  Vec3d origin = Vec3d::Zero();  // Local frame: weighted centroid, tangents, mean normal.
  Vec3d tangent_u = Vec3d::UnitX(), tangent_v = Vec3d::UnitY(), normal = Vec3d::UnitZ();
  double scale = 1;                              // The fitting radius (larger than the support in sparse leaves);
                                                 // tangent coordinates are divided by it.
  std::array<double, kMaxTerms> coefficients{};  // Height polynomial, or quadric in y = (x − origin)/scale.
  int8_t degree = 0;
  int8_t depth = 0;
  bool quadric = false;
  Feature feature = Feature::kSmooth;
  int32_t sharp = -1;  // Index of its SharpFit where the fit has sheets (feature != kSmooth).

  // f(x) and ∇f(x); f > 0 on the side the normals point to.
  double Evaluate(const Vec3d& x, Vec3d* gradient) const {
    const Vec3d d = x - origin;
    if (quadric) {
      const Vec3d y = d / scale;
      const auto& q = coefficients;
      const double value = q[0] + q[1] * y.x() + q[2] * y.y() + q[3] * y.z() + q[4] * y.x() * y.x() +
                           q[5] * y.y() * y.y() + q[6] * y.z() * y.z() + q[7] * y.x() * y.y() + q[8] * y.x() * y.z() +
                           q[9] * y.y() * y.z();
      if (gradient) {
        *gradient = Vec3d(q[1] + 2 * q[4] * y.x() + q[7] * y.y() + q[8] * y.z(),
                          q[2] + 2 * q[5] * y.y() + q[7] * y.x() + q[9] * y.z(),
                          q[3] + 2 * q[6] * y.z() + q[8] * y.x() + q[9] * y.y()) /
                    scale;
      }
      return value;
    }
    BivariatePolynomial p;
    p.coefficients = coefficients;
    p.degree = degree;
    double h, hu, hv;
    p.Evaluate(tangent_u.dot(d) / scale, tangent_v.dot(d) / scale, h, hu, hv);
    if (gradient) *gradient = normal - (hu * tangent_u + hv * tangent_v) / scale;
    return normal.dot(d) - h;
  }
};

struct Node {
  uint32_t x = 0, y = 0, z = 0;
  int level = 0;
  int32_t first_child = -1;  // Children are contiguous; child i has offsets (i&1, i>>1&1, i>>2&1).
  int32_t fit = -1;
};

double Theta(double s2) {
  const double t = 1 - s2;
  return t * t * t * t;
}

}  // namespace

// The input points and what derives from them alone. An edit that keeps the points (set_degree,
// refit) shares them with the function it edits, so it rebuilds no point index.
struct PointData {
  std::vector<Vec3f> positions;
  std::vector<Vec3f> normals;        // Kept for refits of local edits.
  std::vector<float> local_spacing;  // Per point: distance to its kSpacingNeighbors-th neighbour.
  std::unique_ptr<core::KdTree> kd_tree;
};

struct PuFunction::Impl {
  std::shared_ptr<PointData> cloud = std::make_shared<PointData>();  // Not changed once built.
  PuParams params;  // The effective parameters of the fits (after the noise adjustment).
  Vec3d origin = Vec3d::Zero();
  double root_edge = 1;
  int deepest_level = 0;
  std::vector<Node> nodes;
  std::vector<LocalFit> fits;
  std::vector<SharpFit> sharp_fits;
  // For every node (leaves only are filled): the fits whose support meets the node's cube.
  std::vector<uint32_t> influence_offsets;
  std::vector<uint32_t> influence;
  bool coverage_check = true;
  double coverage_factor = 1.25;

  double Edge(int level) const { return std::ldexp(root_edge, -level); }
  Vec3d Centre(const Node& n) const { return origin + (Vec3d(n.x, n.y, n.z) + Vec3d::Constant(0.5)) * Edge(n.level); }

  int32_t LeafAt(const Vec3d& x) const {
    const Vec3d g = (x - origin) / root_edge;
    if (!(g.minCoeff() >= 0 && g.maxCoeff() <= 1)) return -1;
    int32_t index = 0;
    while (nodes[static_cast<size_t>(index)].first_child >= 0) {
      const Node& n = nodes[static_cast<size_t>(index)];
      const Vec3d c = Centre(n);
      const int octant = (x.x() >= c.x() ? 1 : 0) | (x.y() >= c.y() ? 2 : 0) | (x.z() >= c.z() ? 4 : 0);
      index = n.first_child + octant;
    }
    return index;
  }

  double EvaluateFit(const LocalFit& fit, const Vec3d& x, Vec3d* gradient) const {
    return fit.sharp >= 0 ? sharp_fits[static_cast<size_t>(fit.sharp)].Evaluate(x, gradient)
                          : fit.Evaluate(x, gradient);
  }

  // Calls visit(fit, s²) for every fit whose support holds x. Returns the fit whose support
  // comes closest when none holds it (nullptr when none is near at all).
  template <typename Visit>
  const LocalFit* ForEachSupport(const Vec3d& x, Visit&& visit) const {
    const int32_t leaf = LeafAt(x);
    if (leaf < 0) return nullptr;
    const LocalFit* closest = nullptr;
    double closest_s2 = std::numeric_limits<double>::infinity();
    for (uint32_t k = influence_offsets[static_cast<size_t>(leaf)];
         k < influence_offsets[static_cast<size_t>(leaf) + 1]; ++k) {
      const LocalFit& fit = fits[influence[k]];
      const double s2 = (x - fit.centre).squaredNorm() / (fit.support_radius * fit.support_radius);
      if (s2 < 1) visit(fit, s2);
      if (s2 < closest_s2) closest_s2 = s2, closest = &fit;
    }
    return closest;
  }

  core::FieldGradient Evaluate(const Vec3d& x, bool with_gradient, bool decide_defined = true) const {
    double sum_theta = 0, sum_value = 0;
    Vec3d sum_grad_theta = Vec3d::Zero(), sum_grad_value = Vec3d::Zero();
    const LocalFit* closest = ForEachSupport(x, [&](const LocalFit& fit, double s2) {
      const double theta = Theta(s2);
      Vec3d grad_f;
      const double f = EvaluateFit(fit, x, with_gradient ? &grad_f : nullptr);
      sum_theta += theta;
      sum_value += theta * f;
      if (with_gradient) {
        const double t = 1 - s2;
        const Vec3d grad_theta = (-8 * t * t * t / (fit.support_radius * fit.support_radius)) * (x - fit.centre);
        sum_grad_theta += grad_theta;
        sum_grad_value += grad_theta * f + theta * grad_f;
      }
    });
    core::FieldGradient out;
    if (!(sum_theta > 0)) {
      // Between supports (possible next to leaves without points): the closest fit gives the
      // sign, so that tetrahedra there still classify their corners; no surface is placed here.
      out.value = closest ? EvaluateFit(*closest, x, with_gradient ? &out.gradient : nullptr)
                          : std::numeric_limits<double>::quiet_NaN();
      return out;
    }
    out.value = sum_value / sum_theta;
    if (with_gradient)
      out.gradient = (sum_grad_value * sum_theta - sum_value * sum_grad_theta) / (sum_theta * sum_theta);
    out.defined = true;
    if (coverage_check && decide_defined) {
      const core::Neighbor nearest = cloud->kd_tree->Nearest(x.cast<float>());
      const double reach = coverage_factor * cloud->local_spacing[nearest.index];
      out.defined = nearest.distance2 <= reach * reach;
    }
    return out;
  }
};

namespace {

struct BuildContext {
  BuildContext(const PuParams& p, const PuFunction::Impl& m, std::span<const Vec3f> n, double bound)
      : params(p),
        impl(m),
        normals(n),
        error_bound(bound),
        cos_max_angle(std::cos(p.max_normal_angle * M_PI / 180.0)),
        sharp{std::cos(p.sharp_angle * M_PI / 180.0), SharpParams{}.corner_share} {}
  const PuParams& params;
  const PuFunction::Impl& impl;
  std::span<const Vec3f> normals;
  double error_bound;  // ε0 in model units.
  double cos_max_angle;
  SharpParams sharp;
};

struct CellOutcome {
  bool split = false;
  bool has_fit = false;
  bool unmet = false;
  LocalFit fit{};
  std::optional<SharpFit> sharp;           // With fit.feature != kSmooth.
  std::array<uint32_t, 9> child_ranges{};  // Boundaries of the children's point ranges.
};

struct Scratch {
  std::vector<core::Neighbor> neighbors;
  std::vector<double> u, v, w, weight;
  std::vector<double> sample_u, sample_v, sample_w, sample_weight;
  std::vector<char> in_support;
  std::vector<Vec3d> points, normals;
  OrthogonalFitter fitter;
};

// The quadric fallback, fitted with value ±δ at p ± δn (so that it behaves like a signed distance
// and carries the orientation), weighted least squares, slightly regularized: an algebraic sphere
// (a|y|² + b·y + c, as in APSS) unless a general quadric fits the points more than
// kSphereErrorFactor times better. A general quadric fitted where a cell straddles a thin part's
// tip (a cylinder meeting a cap) continues past the tip and leaves a blob that the coverage test
// then cuts open; the sphere closes the tip (measured on capsule fingers 2.5 spacings thick: 13
// boundary edges and vertices 6.3 mm off with general quadrics, closed and 2.6 mm with spheres).
constexpr double kSphereErrorFactor = 2.0;
void FitQuadric(const BuildContext& bc, std::span<const core::Neighbor> points, std::span<const double> weights,
                LocalFit& fit) {
  const double delta = 0.25 * fit.scale;
  Eigen::Matrix<double, 10, 10> normal_matrix = Eigen::Matrix<double, 10, 10>::Zero();
  Eigen::Matrix<double, 10, 1> rhs = Eigen::Matrix<double, 10, 1>::Zero();
  auto add_row = [&](const Vec3d& y, double value, double weight) {
    Eigen::Matrix<double, 10, 1> row;
    row << 1, y.x(), y.y(), y.z(), y.x() * y.x(), y.y() * y.y(), y.z() * y.z(), y.x() * y.y(), y.x() * y.z(),
        y.y() * y.z();
    normal_matrix.selfadjointView<Eigen::Lower>().rankUpdate(row, weight);
    rhs += weight * value * row;
  };
  for (size_t j = 0; j < points.size(); ++j) {
    if (weights[j] <= 0) continue;
    const Vec3d p = bc.impl.cloud->positions[points[j].index].cast<double>();
    const Vec3d n = bc.normals[points[j].index].cast<double>();
    const Vec3d y = (p - fit.origin) / fit.scale;
    add_row(y, 0, weights[j]);
    add_row(y + delta / fit.scale * n, delta, weights[j]);
    add_row(y - delta / fit.scale * n, -delta, weights[j]);
  }
  Eigen::Matrix<double, 10, 10> full = normal_matrix.selfadjointView<Eigen::Lower>();
  // The sphere's coefficients z = (c, b, a) map to the quadric's through `to_quadric`.
  Eigen::Matrix<double, 10, 5> to_quadric = Eigen::Matrix<double, 10, 5>::Zero();
  for (int k = 0; k < 4; ++k) to_quadric(k, k) = 1;
  to_quadric(4, 4) = to_quadric(5, 4) = to_quadric(6, 4) = 1;
  Eigen::Matrix<double, 5, 5> sphere_matrix = to_quadric.transpose() * full * to_quadric;
  sphere_matrix.diagonal().array() += 1e-9 * sphere_matrix.trace() + 1e-300;
  full.diagonal().array() += 1e-9 * full.trace() + 1e-300;
  const Eigen::Matrix<double, 10, 1> sphere =
      to_quadric * sphere_matrix.ldlt().solve(to_quadric.transpose() * rhs).eval();
  const Eigen::Matrix<double, 10, 1> general = full.ldlt().solve(rhs);
  fit.quadric = true;
  fit.degree = kQuadricLabel;
  // Largest Taubin distance |f|/|∇f| over the weighted points.
  auto largest_error = [&](const Eigen::Matrix<double, 10, 1>& c) {
    for (int k = 0; k < 10; ++k) fit.coefficients[static_cast<size_t>(k)] = c[k];
    double worst = 0;
    for (size_t j = 0; j < points.size(); ++j) {
      if (weights[j] <= 0) continue;
      Vec3d gradient;
      const double value = fit.Evaluate(bc.impl.cloud->positions[points[j].index].cast<double>(), &gradient);
      worst = std::max(worst, std::abs(value) / std::max(gradient.norm(), 1e-300));
    }
    return worst;
  };
  const double sphere_error = largest_error(sphere);
  const bool use_sphere = !(largest_error(general) * kSphereErrorFactor < sphere_error);
  const Eigen::Matrix<double, 10, 1>& chosen = use_sphere ? sphere : general;
  fit.coefficients = {};
  for (int k = 0; k < 10; ++k) fit.coefficients[static_cast<size_t>(k)] = chosen[k];
}

// Splits the point range of a cell into its 8 octants (in place) and records the boundaries.
void PartitionOctants(std::span<uint32_t> order, std::span<const Vec3f> positions, const Vec3d& centre,
                      std::array<uint32_t, 9>& bounds, uint32_t begin) {
  auto octant = [&](uint32_t i) {
    const Vec3f& p = positions[i];
    return (p.x() >= centre.x() ? 1 : 0) | (p.y() >= centre.y() ? 2 : 0) | (p.z() >= centre.z() ? 4 : 0);
  };
  std::array<uint32_t, 8> counts{};
  for (uint32_t i : order) ++counts[static_cast<size_t>(octant(i))];
  bounds[0] = begin;
  for (size_t k = 0; k < 8; ++k) bounds[k + 1] = bounds[k] + counts[k];
  std::vector<uint32_t> sorted(order.size());
  std::array<uint32_t, 8> next{};
  for (size_t k = 0; k < 8; ++k) next[k] = bounds[k] - begin;
  for (uint32_t i : order) sorted[next[static_cast<size_t>(octant(i))]++] = i;
  std::copy(sorted.begin(), sorted.end(), order.begin());
}

struct DegreeSearch {
  BivariatePolynomial best;  // The lowest-error oriented fit.
  double best_error = std::numeric_limits<double>::infinity();
  bool accepted = false;  // `best` meets the error bound.
};

// Raises the degree of the height fit over the tangent plane, 0 (1 when more is allowed) to
// `degree_cap`, until the largest error meets the bound; `s` holds the neighbours' tangent
// coordinates, weights and support flags.
DegreeSearch SearchDegree(const BuildContext& bc, const LocalFit& fit, int degree_cap, Scratch& s) {
  const PuParams& params = bc.params;
  const size_t n = s.neighbors.size();
  bool any_in_support = false;
  for (char c : s.in_support) any_in_support |= c != 0;
  if (n > kMaxFitSamples) {
    const size_t stride = (n + kMaxFitSamples - 1) / kMaxFitSamples;
    s.sample_u.clear(), s.sample_v.clear(), s.sample_w.clear(), s.sample_weight.clear();
    for (size_t j = 0; j < n; j += stride) {
      if (s.weight[j] <= 0) continue;
      s.sample_u.push_back(s.u[j]), s.sample_v.push_back(s.v[j]), s.sample_w.push_back(s.w[j]);
      s.sample_weight.push_back(s.weight[j]);
    }
    s.fitter.Reset(s.sample_u, s.sample_v, s.sample_w, s.sample_weight);
  } else {
    s.fitter.Reset(s.u, s.v, s.w, s.weight);
  }
  DegreeSearch out;
  for (int degree = 0; degree <= degree_cap; ++degree) {
    if (degree > 0 && !s.fitter.RaiseDegree()) break;  // Rank deficient: the data cannot say more.
    if (degree == 0 && degree_cap > 0) continue;       // A tilted plane is never worse.
    const BivariatePolynomial& p = s.fitter.polynomial();
    // Taubin distance |f|/|∇f|, measured where the leaf's weight is (MPU's rule), and criterion
    // 4, orientation: the fit must agree with its points' normals.
    auto measure = [&](size_t stride, double& error) {
      error = 0;
      size_t inverted = 0, counted = 0;
      for (size_t j = 0; j < n; j += stride) {
        if (any_in_support && !s.in_support[j]) continue;
        double h, hu, hv;
        p.Evaluate(s.u[j], s.v[j], h, hu, hv);
        const Vec3d gradient = fit.normal - (hu * fit.tangent_u + hv * fit.tangent_v) / fit.scale;
        error = std::max(error, std::abs(s.w[j] - h) / gradient.norm());
        ++counted;
        inverted += gradient.dot(bc.normals[s.neighbors[j].index].cast<double>()) <= 0;
      }
      return !params.orientation_check ||
             static_cast<double>(inverted) <= kMaxInvertedShare * static_cast<double>(counted);
    };
    // On large balls a subsample rejects most fits cheaply (its largest error is a lower bound);
    // only a fit that passes there is measured on every point.
    double error = 0;
    const size_t stride = std::max<size_t>(1, n / kMaxFitSamples);
    bool oriented = measure(stride, error);
    if (stride > 1 && oriented && error <= bc.error_bound) oriented = measure(1, error);
    if (!oriented) continue;
    if (error < out.best_error) {
      out.best_error = error;
      out.best = p;
    }
    if (error <= bc.error_bound) {
      out.accepted = true;
      break;
    }
  }
  return out;
}

// Sharp fits are tried in cells of at most this many points whose smooth fit fails (MPU tries
// them only below 2 × N_min; larger cells of a CAD part's faces fit as well, in fewer cells).
constexpr size_t kMaxSharpPoints = 128;

struct SharpOutcome {
  SharpFit fit;
  double error = 0;  // Largest Taubin distance over the support's points.
};

// A sharp fit over the cell's weighted points (sharp_fit.h) measured like the smooth ones, or
// nothing when the normals show no crease, the sheets do not combine, or (criterion 4) the fit
// opposes more than kMaxInvertedShare of its points' normals.
std::optional<SharpOutcome> TrySharp(const BuildContext& bc, double fit_radius, Scratch& s) {
  const size_t n = s.neighbors.size();
  if (!bc.params.sharp || n > kMaxSharpPoints || n < 2) return std::nullopt;
  s.points.resize(n);
  s.normals.resize(n);
  for (size_t j = 0; j < n; ++j) {
    s.points[j] = bc.impl.cloud->positions[s.neighbors[j].index].cast<double>();
    s.normals[j] = bc.normals[s.neighbors[j].index].cast<double>();
  }
  std::optional<SharpFit> fit = FitSharp(s.points, s.normals, s.weight, fit_radius, bc.sharp, s.fitter);
  if (!fit) return std::nullopt;
  bool any_in_support = false;
  for (char c : s.in_support) any_in_support |= c != 0;
  SharpOutcome out{*fit, 0.0};
  size_t inverted = 0, counted = 0;
  for (size_t j = 0; j < n; ++j) {
    if (any_in_support && !s.in_support[j]) continue;
    Vec3d gradient;
    const double f = fit->Evaluate(s.points[j], &gradient);
    out.error = std::max(out.error, std::abs(f) / gradient.norm());
    ++counted;
    inverted += gradient.dot(s.normals[j]) <= 0;
  }
  if (bc.params.orientation_check && static_cast<double>(inverted) > kMaxInvertedShare * static_cast<double>(counted)) {
    return std::nullopt;
  }
  return out;
}

void UseSharp(CellOutcome& out, SharpOutcome&& sharp) {
  out.fit.feature = sharp.fit.feature;
  int degree = 0;
  for (int k = 0; k < sharp.fit.count; ++k)
    degree = std::max(degree, sharp.fit.sheets[static_cast<size_t>(k)].height.degree);
  out.fit.degree = static_cast<int8_t>(degree);
  out.fit.quadric = false;
  out.sharp = std::move(sharp.fit);
}

// The twofold adaptive decision for one cell (seed §2; METHODS §1.5): fit, raise the degree
// while the error is above the bound, split when the highest degree fails. Where the normals show
// an edge or a corner and the smooth fit fails, a sharp fit that meets the bound ends the split.
CellOutcome ProcessCell(const BuildContext& bc, const Node& node, std::span<uint32_t> inside, uint32_t begin,
                        Scratch& s) {
  const PuParams& params = bc.params;
  const PuFunction::Impl& impl = bc.impl;
  CellOutcome out;
  const Vec3d centre = impl.Centre(node);
  const double support = params.support_factor * kSqrt3 * impl.Edge(node.level);
  auto split = [&] {
    out.split = true;
    PartitionOctants(inside, impl.cloud->positions, centre, out.child_ranges, begin);
    return out;
  };
  if (inside.size() > kMaxPointsToFit && node.level < params.max_depth) return split();

  const Vec3f query = centre.cast<float>();
  impl.cloud->kd_tree->Radius(query, static_cast<float>(support), s.neighbors);
  // Splitting helps only while the support holds enough points; past that the fitting ball
  // has to grow, and smaller cells would see the same points.
  const bool can_split = node.level < params.max_depth && s.neighbors.size() >= static_cast<size_t>(params.min_points);
  double fit_radius = support;
  if (s.neighbors.size() < static_cast<size_t>(params.min_points)) {
    impl.cloud->kd_tree->Knn(query, static_cast<size_t>(params.min_points), s.neighbors);
    fit_radius =
        std::min(kMaxRadiusGrowth * support, 1.05 * std::sqrt(static_cast<double>(s.neighbors.back().distance2)));
    impl.cloud->kd_tree->Radius(query, static_cast<float>(fit_radius), s.neighbors);
  }
  const size_t n = s.neighbors.size();
  s.weight.resize(n);
  s.in_support.resize(n);
  Vec3d centroid = Vec3d::Zero(), normal_sum = Vec3d::Zero();
  double weight_sum = 0;
  size_t weighted = 0;
  for (size_t j = 0; j < n; ++j) {
    const double d2 = s.neighbors[j].distance2;
    s.weight[j] = d2 < fit_radius * fit_radius ? Theta(d2 / (fit_radius * fit_radius)) : 0.0;
    s.in_support[j] = d2 <= support * support;
    weighted += s.weight[j] > 0;
    weight_sum += s.weight[j];
    centroid += s.weight[j] * impl.cloud->positions[s.neighbors[j].index].cast<double>();
    normal_sum += s.weight[j] * bc.normals[s.neighbors[j].index].cast<double>();
  }
  if (!(weight_sum > 0)) return out;
  LocalFit& fit = out.fit;
  out.has_fit = true;
  fit.centre = centre;
  fit.support_radius = support;
  fit.origin = centroid / weight_sum;
  fit.scale = fit_radius;
  fit.depth = static_cast<int8_t>(node.level);
  fit.quadric = false;
  const double normal_length = normal_sum.norm();
  fit.normal = normal_length > 0 ? Vec3d(normal_sum / normal_length) : Vec3d::UnitZ();
  double min_cos = normal_length > 0 ? 1.0 : -1.0;
  for (size_t j = 0; j < n; ++j) {
    min_cos = std::min(min_cos, bc.normals[s.neighbors[j].index].cast<double>().dot(fit.normal));
  }
  // Criterion 1, the normal cone: no height field over the mean tangent plane otherwise.
  if (min_cos < bc.cos_max_angle) {
    if (auto sharp = TrySharp(bc, fit_radius, s); sharp && sharp->error <= bc.error_bound) {
      UseSharp(out, *std::move(sharp));
      return out;
    }
    if (can_split) return split();
    FitQuadric(bc, s.neighbors, s.weight, fit);
    return out;
  }
  fit.tangent_u = fit.normal.unitOrthogonal();
  fit.tangent_v = fit.normal.cross(fit.tangent_u);
  s.u.resize(n), s.v.resize(n), s.w.resize(n);
  // Criterion 3a, coverage of the tangent disk around the projected cell centre.
  const Vec3d centre_offset = centre - fit.origin;
  const double uc = fit.tangent_u.dot(centre_offset) / fit.scale, vc = fit.tangent_v.dot(centre_offset) / fit.scale;
  unsigned sectors = 0;
  for (size_t j = 0; j < n; ++j) {
    const Vec3d d = impl.cloud->positions[s.neighbors[j].index].cast<double>() - fit.origin;
    s.u[j] = fit.tangent_u.dot(d) / fit.scale;
    s.v[j] = fit.tangent_v.dot(d) / fit.scale;
    s.w[j] = fit.normal.dot(d);
    const double du = s.u[j] - uc, dv = s.v[j] - vc;
    if (du * du + dv * dv <= 1) {
      sectors |= 1u << ((dv < 0 ? 4 : 0) | (du < 0 ? 2 : 0) | (std::abs(du) < std::abs(dv) ? 1 : 0));
    }
  }
  int degree_cap = params.max_degree;
  if (params.coverage_check && std::popcount(sectors) < 7) degree_cap = std::min(degree_cap, 1);
  // Criterion 2: twice as many points as coefficients.
  while (degree_cap > 0 && weighted < static_cast<size_t>(2 * TermCount(degree_cap))) --degree_cap;

  const DegreeSearch search = SearchDegree(bc, fit, degree_cap, s);
  const bool accepted = search.accepted;
  const double best_error = search.best_error;
  const BivariatePolynomial& best = search.best;
  if (!accepted) {
    std::optional<SharpOutcome> sharp = TrySharp(bc, fit_radius, s);
    if (sharp && (sharp->error <= bc.error_bound || (!can_split && sharp->error < best_error))) {
      out.unmet = sharp->error > bc.error_bound;
      UseSharp(out, *std::move(sharp));
      return out;
    }
  }
  if (!accepted && can_split) return split();
  if (!std::isfinite(best_error)) {
    FitQuadric(bc, s.neighbors, s.weight, fit);
    return out;
  }
  out.unmet = !accepted;
  fit.coefficients = best.coefficients;
  fit.degree = static_cast<int8_t>(best.degree);
  return out;
}

}  // namespace

const core::ParamTable<PuParams>& PuParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuParams>();
    t->Real<&PuParams::error_threshold>("error_threshold", 1e-6, 0.1, "share of the diagonal",
                                        "largest fitting error accepted in a cell; set it near the noise amplitude "
                                        "for noisy scans")
        .Integer<&PuParams::max_depth>("max_depth", 1, 18, "levels", "octree levels below the root cube")
        .Integer<&PuParams::max_degree>("max_degree", 0, kMaxDegree, "", "highest polynomial degree of a local fit")
        .Real<&PuParams::support_factor>("support_factor", 0.55, 2, "cell diagonals", "support radius of a cell")
        .Integer<&PuParams::min_points>("min_points", 4, 200, "points",
                                        "the fitting ball of a sparse cell grows until it holds this many points")
        .Real<&PuParams::max_normal_angle>("max_normal_angle", 10, 180, "degrees",
                                           "normal-cone criterion: wider cells are split (180 disables it)")
        .Flag<&PuParams::coverage_check>("coverage", "coverage criteria: no sheets away from the data, holes stay open")
        .Real<&PuParams::coverage_factor>("coverage_factor", 0.5, 20, "local spacings",
                                          "surface only within this many local spacings (distance to the 8th "
                                          "neighbour) of a data point")
        .Flag<&PuParams::orientation_check>("orientation_check",
                                            "reject fits whose gradient opposes their points' normals")
        .Real<&PuParams::noise_level>("noise_level", -1, 0.1, "share of the diagonal",
                                      "scan noise sigma; -1 estimates it, 0 declares the data exact; above "
                                      "error_threshold the threshold becomes 3 sigma and min_points at least 80")
        .Flag<&PuParams::sharp>("sharp",
                                "sharp edges and corners: where a cell's smooth fit fails and its normals split "
                                "into clusters, one sheet per cluster combined by max/min")
        .Real<&PuParams::sharp_angle>("sharp_angle", 5, 90, "degrees",
                                      "normals of one cell wider apart than this show an edge")
        .AddRule([](const PuParams& p) {
          return p.noise_level == -1 || p.noise_level >= 0
                     ? absl::OkStatus()
                     : absl::InvalidArgumentError(
                           core::StrCat("noise_level=", p.noise_level, " must be -1 (estimate it) or within [0, 0.1]"));
        });
    return t;
  }();
  return *table;
}

absl::Status Validate(const PuParams& p) { return PuParamTable().Validate(p); }

const core::ParamTable<PuExtractParams>& PuExtractParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuExtractParams>();
    t->Real<&PuExtractParams::cell_size>("cell_size", 0.25, 64, "mean point spacings",
                                         "smallest extraction cell at the surface (rounded to an octree level); cells "
                                         "near the data are up to 8x larger where the surface is flat enough");
    t->Real<&PuExtractParams::chord_error>("chord_error", 0, 0.01, "share of the diagonal",
                                           "cells are split towards cell_size where flat triangles would stray "
                                           "farther than this from the surface; 0 = finest cells everywhere");
    t->Include(&PuExtractParams::marching, extract::MarchingParamTable());
    return t;
  }();
  return *table;
}

PuFunction::PuFunction() : impl_(std::make_unique<Impl>()) {}
PuFunction::~PuFunction() = default;

core::FieldValue PuFunction::Value(const Vec3d& x) const {
  const core::FieldGradient g = impl_->Evaluate(x, false);
  return {g.value, g.defined};
}

double PuFunction::ValueOnly(const Vec3d& x) const { return impl_->Evaluate(x, false, false).value; }

core::FieldGradient PuFunction::ValueAndGradient(const Vec3d& x) const { return impl_->Evaluate(x, true); }

core::FieldGradient PuFunction::ValueAndGradientOnly(const Vec3d& x) const {
  core::FieldGradient g = impl_->Evaluate(x, true, false);
  g.defined = std::isfinite(g.value);
  return g;
}

FitLabel PuFunction::DominantFit(const Vec3d& x) const {
  FitLabel label;
  double best = 0;
  impl_->ForEachSupport(x, [&](const LocalFit& fit, double s2) {
    if (const double theta = Theta(s2); theta > best) {
      best = theta;
      label = {fit.depth, fit.degree, static_cast<int>(fit.feature)};
    }
  });
  return label;
}

namespace {

// The point spacing statistics: with coverage checks, one neighbour query per point gives both
// the local spacing (kept for evaluation) and the nearest distance (averaged for the stats).
absl::Status MeasureSpacing(PuFunction::Impl& impl, bool coverage_check, PuStats& stats, core::JobContext& ctx) {
  if (!coverage_check) {
    stats.mean_spacing = core::MeanNearestNeighborDistance(*impl.cloud->kd_tree);
    return absl::OkStatus();
  }
  impl.cloud->local_spacing.resize(impl.cloud->positions.size());
  std::vector<float> nearest(impl.cloud->positions.size());
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      impl.cloud->positions.size(), 2048,
      [&](size_t b, size_t e) {
        std::vector<core::Neighbor> knn;
        for (size_t i = b; i < e; ++i) {
          impl.cloud->kd_tree->Knn(impl.cloud->positions[i], kSpacingNeighbors + 1, knn);
          impl.cloud->local_spacing[i] = std::sqrt(knn.back().distance2);
          nearest[i] = std::sqrt(knn[1].distance2);
        }
      },
      &ctx));
  double sum = 0;
  for (float d : nearest) sum += d;
  stats.mean_spacing = sum / static_cast<double>(nearest.size());
  return absl::OkStatus();
}

// Noise-aware bounds: a largest-error test cannot pass below about 3σ on noisy points, and fits
// over few noisy points follow the noise (blobs, bumps), so where the noise exceeds the requested
// accuracy both are raised.
PuParams NoiseAwareParams(const PuFunction::Impl& impl, std::span<const Vec3f> normals, const PuParams& params,
                          double diagonal, PuStats& stats) {
  const core::NoiseEstimate noise = core::EstimateNoise(*impl.cloud->kd_tree, normals,
                                                        params.noise_level >= 0 ? params.noise_level * diagonal : -1.0);
  stats.noise_estimate = noise.sigma / diagonal;
  PuParams effective = params;
  if (stats.noise_estimate > params.error_threshold) {
    effective.error_threshold = kNoiseBoundFactor * stats.noise_estimate;
    effective.min_points = std::max({params.min_points, kNoisyMinPoints, static_cast<int>(noise.points_in_ball)});
    // Noisy normals split into false clusters (measured: bunny and fandisk at σ = 0.25 % came out
    // worse, fandisk open): sharp fits only on data cleaner than the requested accuracy.
    effective.sharp = false;
  }
  stats.error_threshold = effective.error_threshold;
  stats.min_points = effective.min_points;
  return effective;
}

// The fitting tree below the `current` leaves, level by level: every cell of a level is fitted in
// parallel, then split or kept (with its fit) in order, so the tree does not depend on the thread
// count. `ranges[node]` is the node's slice of `order` (the indices of the points in its cube);
// `stats` per-depth vectors must hold max_depth + 1 entries.
absl::Status GrowSubtrees(const BuildContext& bc, PuFunction::Impl& impl, std::vector<uint32_t>& order,
                          std::vector<std::array<uint32_t, 2>>& ranges, std::vector<int32_t> current, int max_depth,
                          PuStats& stats, core::JobContext& ctx) {
  for (int level = 0; !current.empty(); ++level) {  // `level`: steps below the start nodes.
    core::SubContext level_ctx(ctx, core::StrCat("fitting level ", level), static_cast<double>(level) / (max_depth + 1),
                               static_cast<double>(level + 1) / (max_depth + 1));
    std::vector<CellOutcome> outcomes(current.size());
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        current.size(), 8,
        [&](size_t b, size_t e) {
          thread_local Scratch scratch;
          for (size_t i = b; i < e; ++i) {
            const auto index = static_cast<size_t>(current[i]);
            const auto [lo, hi] = ranges[index];
            outcomes[i] = ProcessCell(bc, impl.nodes[index], std::span(order).subspan(lo, hi - lo), lo, scratch);
          }
        },
        &ctx, [&](double f) { level_ctx.Report(f); }));
    stats.cells_examined += static_cast<int64_t>(current.size());
    std::vector<int32_t> next;
    for (size_t i = 0; i < current.size(); ++i) {
      CellOutcome& o = outcomes[i];
      const auto index = static_cast<size_t>(current[i]);
      if (o.split) {
        if (impl.nodes.size() + 8 > static_cast<size_t>(std::numeric_limits<int32_t>::max())) {
          return absl::ResourceExhaustedError("the PU tree needs more than 2^31 cells; raise error_threshold");
        }
        const Node parent = impl.nodes[index];
        impl.nodes[index].first_child = static_cast<int32_t>(impl.nodes.size());
        impl.nodes[index].fit = -1;
        for (uint32_t k = 0; k < 8; ++k) {
          next.push_back(static_cast<int32_t>(impl.nodes.size()));
          impl.nodes.push_back(Node{2 * parent.x + (k & 1), 2 * parent.y + ((k >> 1) & 1),
                                    2 * parent.z + ((k >> 2) & 1), parent.level + 1, -1, -1});
          ranges.push_back({o.child_ranges[k], o.child_ranges[k + 1]});
        }
        continue;
      }
      const int depth = impl.nodes[index].level;
      ++stats.leaves_per_depth[static_cast<size_t>(depth)];
      impl.deepest_level = std::max(impl.deepest_level, depth);
      if (!o.has_fit) continue;
      impl.nodes[index].fit = static_cast<int32_t>(impl.fits.size());
      ++stats.fits_per_depth[static_cast<size_t>(depth)];
      if (o.sharp) {
        o.fit.sharp = static_cast<int32_t>(impl.sharp_fits.size());
        impl.sharp_fits.push_back(*o.sharp);
        ++(o.fit.feature == Feature::kCorner ? stats.sharp_corners : stats.sharp_edges);
      } else if (o.fit.quadric) {
        ++stats.quadric_fits;
      } else {
        ++stats.fits_per_degree[static_cast<size_t>(o.fit.degree)];
      }
      stats.unmet_threshold += o.unmet;
      impl.fits.push_back(o.fit);
    }
    current = std::move(next);
  }
  return absl::OkStatus();
}

absl::Status GrowFittingTree(const BuildContext& bc, PuFunction::Impl& impl, size_t points, int max_depth,
                             PuStats& stats, core::JobContext& ctx) {
  std::vector<uint32_t> order(points);
  for (uint32_t i = 0; i < order.size(); ++i) order[i] = i;
  std::vector<std::array<uint32_t, 2>> ranges{{0, static_cast<uint32_t>(order.size())}};
  impl.nodes.push_back(Node{});
  stats.leaves_per_depth.assign(static_cast<size_t>(max_depth) + 1, 0);
  stats.fits_per_depth.assign(static_cast<size_t>(max_depth) + 1, 0);
  return GrowSubtrees(bc, impl, order, ranges, {0}, max_depth, stats, ctx);
}

// Whether a fit's support meets a node's cube: the one test behind the influence lists.
bool SupportMeetsCube(const PuFunction::Impl& impl, const LocalFit& fit, const Node& n) {
  const Vec3d lo = impl.origin + Vec3d(n.x, n.y, n.z) * impl.Edge(n.level);
  const Vec3d hi = lo + Vec3d::Constant(impl.Edge(n.level));
  const Vec3d nearest = fit.centre.cwiseMax(lo).cwiseMin(hi);
  return (nearest - fit.centre).squaredNorm() < fit.support_radius * fit.support_radius;
}

// Calls emit(leaf) for every leaf of the tree whose cube the fit's support meets.
template <typename Emit>
void ForEachLeafInSupport(const PuFunction::Impl& impl, const LocalFit& fit, Emit&& emit) {
  std::vector<int32_t> stack{0};
  while (!stack.empty()) {
    const int32_t id = stack.back();
    const Node& n = impl.nodes[static_cast<size_t>(id)];
    stack.pop_back();
    if (!SupportMeetsCube(impl, fit, n)) continue;
    if (n.first_child < 0) {
      emit(id);
    } else {
      for (int k = 0; k < 8; ++k) stack.push_back(n.first_child + k);
    }
  }
}

// Leaf → fits whose support meets it, so that an evaluation visits one short list.
absl::Status IndexInfluence(PuFunction::Impl& impl, core::JobContext& ctx) {
  std::vector<uint32_t> leaf_counts(impl.nodes.size() + 1, 0);
  std::vector<std::vector<std::pair<uint32_t, uint32_t>>> pairs_per_chunk;
  std::mutex chunks_mutex;
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      impl.fits.size(), 256,
      [&](size_t b, size_t e) {
        std::vector<std::pair<uint32_t, uint32_t>> pairs;
        for (size_t f = b; f < e; ++f) {
          ForEachLeafInSupport(impl, impl.fits[f], [&](int32_t leaf) {
            pairs.emplace_back(static_cast<uint32_t>(leaf), static_cast<uint32_t>(f));
          });
        }
        std::lock_guard lock(chunks_mutex);
        pairs_per_chunk.push_back(std::move(pairs));
      },
      &ctx));
  for (const auto& chunk : pairs_per_chunk) {
    for (const auto& [leaf, fit] : chunk) ++leaf_counts[leaf + 1];
  }
  for (size_t i = 1; i < leaf_counts.size(); ++i) leaf_counts[i] += leaf_counts[i - 1];
  impl.influence_offsets = leaf_counts;
  impl.influence.resize(leaf_counts.back());
  for (const auto& chunk : pairs_per_chunk) {
    for (const auto& [leaf, fit] : chunk) impl.influence[leaf_counts[leaf]++] = fit;
  }
  // In fit order, so that sums (and a rebuilt index) do not depend on the threads' timing.
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      impl.nodes.size(), 4096,
      [&](size_t b, size_t e) {
        for (size_t leaf = b; leaf < e; ++leaf) {
          std::sort(impl.influence.begin() + impl.influence_offsets[leaf],
                    impl.influence.begin() + impl.influence_offsets[leaf + 1]);
        }
      },
      &ctx));
  return absl::OkStatus();
}

// IndexInfluence for an edit, without visiting every fit again. `after` is `before` with the
// fits of the `touched` leaves replaced by `new_fits` (indices in `after`; a touched leaf may
// have been split) and the fits renumbered by `renumber` (before's index → after's; empty when
// unchanged). An unchanged fit meets the same cubes as before, so only the leaves that a
// replaced or a new support meets, and the leaves new to the tree, get their lists rebuilt; the
// rest are renumbered. The result equals IndexInfluence(after) entry for entry.
absl::Status UpdateInfluence(const PuFunction::Impl& before, PuFunction::Impl& after, std::span<const int32_t> touched,
                             std::span<const int32_t> new_fits, std::span<const int32_t> renumber,
                             core::JobContext& ctx) {
  const size_t old_nodes = before.nodes.size(), nodes = after.nodes.size();
  auto is_leaf = [&](size_t node) { return after.nodes[node].first_child < 0; };
  auto to_after = [&](uint32_t fit) { return renumber.empty() ? static_cast<int32_t>(fit) : renumber[fit]; };
  std::vector<char> replaced(before.fits.size(), 0);
  for (int32_t t : touched) replaced[static_cast<size_t>(before.nodes[static_cast<size_t>(t)].fit)] = 1;
  // Rebuilt lists: rebuilt[slot[leaf]]; `source[leaf]`, the before-leaf whose list it starts from.
  std::vector<int32_t> slot(nodes, -1), source(nodes, -1);
  std::vector<int32_t> rebuilt_leaves;
  auto mark = [&](int32_t leaf, int32_t from) {
    if (slot[static_cast<size_t>(leaf)] >= 0) return;
    slot[static_cast<size_t>(leaf)] = static_cast<int32_t>(rebuilt_leaves.size());
    source[static_cast<size_t>(leaf)] = from;
    rebuilt_leaves.push_back(leaf);
  };
  for (int32_t t : touched) {  // Leaves new to the tree start from the split leaf's list.
    std::vector<int32_t> stack{t};
    while (!stack.empty()) {
      const int32_t id = stack.back();
      stack.pop_back();
      const Node& n = after.nodes[static_cast<size_t>(id)];
      if (n.first_child < 0) {
        mark(id, t);
      } else {
        for (int32_t k = 0; k < 8; ++k) stack.push_back(n.first_child + k);
      }
    }
  }
  for (int32_t t : touched) {
    ForEachLeafInSupport(before, before.fits[static_cast<size_t>(before.nodes[static_cast<size_t>(t)].fit)],
                         [&](int32_t leaf) {
                           if (is_leaf(static_cast<size_t>(leaf))) mark(leaf, leaf);
                         });
  }
  std::vector<std::pair<int32_t, int32_t>> added;  // (leaf, new fit)
  for (int32_t f : new_fits) {
    ForEachLeafInSupport(after, after.fits[static_cast<size_t>(f)], [&](int32_t leaf) {
      mark(leaf, leaf);  // A leaf new to the tree is marked already, from its split leaf.
      added.emplace_back(leaf, f);
    });
  }
  std::vector<std::vector<uint32_t>> rebuilt(rebuilt_leaves.size());
  for (size_t i = 0; i < rebuilt_leaves.size(); ++i) {
    const auto leaf = static_cast<size_t>(rebuilt_leaves[i]);
    const int32_t from = source[leaf];
    const bool new_leaf = leaf >= old_nodes;
    for (uint32_t k = before.influence_offsets[static_cast<size_t>(from)];
         k < before.influence_offsets[static_cast<size_t>(from) + 1]; ++k) {
      const uint32_t fit = before.influence[k];
      if (replaced[fit]) continue;
      const int32_t now = to_after(fit);
      if (new_leaf && !SupportMeetsCube(after, after.fits[static_cast<size_t>(now)], after.nodes[leaf])) continue;
      rebuilt[i].push_back(static_cast<uint32_t>(now));
    }
  }
  for (const auto& [leaf, fit] : added)
    rebuilt[static_cast<size_t>(slot[static_cast<size_t>(leaf)])].push_back(static_cast<uint32_t>(fit));
  for (std::vector<uint32_t>& list : rebuilt) std::sort(list.begin(), list.end());
  std::vector<uint32_t>& offsets = after.influence_offsets;
  offsets.assign(nodes + 1, 0);
  for (size_t node = 0; node < nodes; ++node) {
    uint32_t count = 0;
    if (slot[node] >= 0) {
      count = static_cast<uint32_t>(rebuilt[static_cast<size_t>(slot[node])].size());
    } else if (node < old_nodes && is_leaf(node)) {
      count = before.influence_offsets[node + 1] - before.influence_offsets[node];
    }
    offsets[node + 1] = offsets[node] + count;
  }
  after.influence.resize(offsets.back());
  return core::ParallelFor(
      nodes, 4096,
      [&](size_t b, size_t e) {
        for (size_t node = b; node < e; ++node) {
          uint32_t* out = after.influence.data() + offsets[node];
          if (slot[node] >= 0) {
            const std::vector<uint32_t>& list = rebuilt[static_cast<size_t>(slot[node])];
            std::copy(list.begin(), list.end(), out);
          } else if (offsets[node + 1] > offsets[node]) {
            for (uint32_t k = before.influence_offsets[node]; k < before.influence_offsets[node + 1]; ++k) {
              *out++ = static_cast<uint32_t>(to_after(before.influence[k]));
            }
          }
        }
      },
      &ctx);
}

}  // namespace

absl::StatusOr<std::unique_ptr<PuFunction>> BuildPu(const core::PointCloud& cloud, const PuParams& params,
                                                    core::JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (!cloud.has_normals()) return absl::InvalidArgumentError("PU surfaces need oriented normals");
  if (cloud.size() < 4) return absl::InvalidArgumentError("PU surfaces need at least 4 points");
  if (cloud.size() >= std::numeric_limits<uint32_t>::max()) return absl::InvalidArgumentError("too many points");
  const auto start = std::chrono::steady_clock::now();
  std::unique_ptr<PuFunction> function(new PuFunction());
  PuFunction::Impl& impl = *function->impl_;
  PuStats& stats = function->stats_;
  // Morton (Z-curve) order: points close in space are close in memory, which makes the index
  // build and every neighbour query cache-friendly (4M points: the spacing pass 2.5× faster).
  const std::vector<uint32_t> order = core::MortonOrder(cloud.positions);
  impl.cloud->positions.resize(cloud.size());
  impl.cloud->normals.resize(cloud.size());
  for (size_t i = 0; i < order.size(); ++i) {
    impl.cloud->positions[i] = cloud.positions[order[i]];
    impl.cloud->normals[i] = cloud.normals[order[i]];
  }
  impl.cloud->kd_tree = std::make_unique<core::KdTree>(impl.cloud->positions);
  impl.coverage_check = params.coverage_check;
  impl.coverage_factor = params.coverage_factor;
  LSQSURF_RETURN_IF_ERROR(MeasureSpacing(impl, params.coverage_check, stats, ctx));
  stats.spacing_seconds = core::SecondsSince(start);
  const core::Box3 box = core::BoundingBox(impl.cloud->positions);
  const double diagonal = core::Diagonal(box);
  if (!(diagonal > 0)) return absl::InvalidArgumentError("all points coincide");
  // The root cube: 1.2 × the largest side, as in MPU, so that boundary cells have margin.
  impl.root_edge = 1.2 * box.sizes().maxCoeff();
  impl.origin = box.center() - Vec3d::Constant(impl.root_edge / 2);
  stats.root_edge = impl.root_edge;
  const PuParams effective = NoiseAwareParams(impl, impl.cloud->normals, params, diagonal, stats);
  impl.params = effective;
  const BuildContext bc(effective, impl, impl.cloud->normals, effective.error_threshold * diagonal);
  LSQSURF_RETURN_IF_ERROR(GrowFittingTree(bc, impl, cloud.size(), params.max_depth, stats, ctx));
  stats.fit_seconds = core::SecondsSince(start);
  const auto index_start = std::chrono::steady_clock::now();
  LSQSURF_RETURN_IF_ERROR(IndexInfluence(impl, ctx));
  stats.index_seconds = core::SecondsSince(index_start);
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  if (impl.fits.empty()) return absl::FailedPreconditionError("no local fit could be made");
  return function;
}

namespace {

// Around the data, extraction cells are at most 2^this times the finest (8×: 40 spacings by
// default) where the surface is flat; one level more changed nothing on the bench shapes.
constexpr int kCoarseExtractionLevels = 3;

int ExtractionDepth(double root_edge, double target) {
  return std::clamp(static_cast<int>(std::lround(std::log2(root_edge / target))), 2,
                    extract::AdaptiveOctree::kMaxDepth);
}

// The extraction cells of levels [from, to) that a sharp fit's support meets: creases go to the
// finest cells, where the crease splitting places them (their curvature is not a chord's).
absl::flat_hash_set<uint64_t> CellsNearSharpFits(const PuFunction::Impl& impl, const extract::AdaptiveOctree& tree,
                                                 int from, int to, const core::Box3* region) {
  absl::flat_hash_set<uint64_t> cells;
  for (const LocalFit& fit : impl.fits) {
    if (fit.feature == Feature::kSmooth) continue;
    const Vec3d reach = Vec3d::Constant(fit.support_radius);
    if (region != nullptr && (((fit.centre + reach).array() < region->min().array()).any() ||
                              ((fit.centre - reach).array() > region->max().array()).any())) {
      continue;
    }
    for (int level = from; level < to; ++level) {
      const double edge = tree.CellEdge(level);
      const int64_t n = int64_t{1} << level;
      const auto index = [&](double v) { return std::clamp<int64_t>(static_cast<int64_t>(std::floor(v)), 0, n - 1); };
      const Vec3d lo = (fit.centre - tree.origin()) / edge - Vec3d::Constant(fit.support_radius / edge);
      const Vec3d hi = (fit.centre - tree.origin()) / edge + Vec3d::Constant(fit.support_radius / edge);
      for (int64_t z = index(lo.z()); z <= index(hi.z()); ++z)
        for (int64_t y = index(lo.y()); y <= index(hi.y()); ++y)
          for (int64_t x = index(lo.x()); x <= index(hi.x()); ++x) {
            cells.insert(extract::CellKey(
                {level, static_cast<uint32_t>(x), static_cast<uint32_t>(y), static_cast<uint32_t>(z)}));
          }
    }
  }
  return cells;
}

// Extract's J1a tree (2:1 balanced) and the finest cells that hold points (where tracking starts).
struct ExtractionTree {
  explicit ExtractionTree(const core::Box3& root, int depth) : tree(root, depth) {}
  extract::AdaptiveOctree tree;
  std::vector<extract::OctreeCell> start;
};

// Extract's finest level (from `cell_size`) and the coarsest it allows around the data.
struct ExtractionLevels {
  int finest = 0;
  int band = 0;
};
absl::StatusOr<ExtractionLevels> LevelsFor(const PuFunction& function, const PuExtractParams& params) {
  if (!(params.cell_size > 0) || !std::isfinite(params.cell_size)) {
    return absl::InvalidArgumentError("cell_size must be a positive number");
  }
  const double target = params.cell_size * function.stats().mean_spacing;
  if (!(target > 0)) return absl::InvalidArgumentError("the points have no spacing to size cells by");
  const int finest = ExtractionDepth(function.stats().root_edge, target);
  return ExtractionLevels{finest, std::max(1, finest - kCoarseExtractionLevels)};
}

// The finest extraction level comes from `cell_size`; around the data the tree is refined to at
// least kCoarseExtractionLevels levels above it, and finer where flat triangles would stray from
// the surface by more than `chord_error`, or where a sharp fit makes a crease. With `region`, only
// the points and sharp fits in that box are looked at: inside it, away from its sides by a few
// coarse cells, the tree is the whole one's (every decision is local).
absl::StatusOr<std::unique_ptr<ExtractionTree>> BuildExtractionTree(const PuFunction& function,
                                                                    const PuFunction::Impl& impl,
                                                                    const PuExtractParams& params,
                                                                    const core::Box3* region, core::JobContext& ctx) {
  const auto levels = LevelsFor(function, params);
  if (!levels.ok()) return levels.status();
  const int depth = levels->finest, band_level = levels->band;
  auto built =
      std::make_unique<ExtractionTree>(core::Box3(impl.origin, impl.origin + Vec3d::Constant(impl.root_edge)), depth);
  extract::AdaptiveOctree& tree = built->tree;
  std::vector<Vec3f> local_points;
  std::span<const Vec3f> points = impl.cloud->positions;
  if (region != nullptr) {
    for (const Vec3f& p : impl.cloud->positions) {
      if (region->contains(p.cast<double>())) local_points.push_back(p);
    }
    points = local_points;
  }
  extract::SurfaceBand band = extract::MarkSurfaceBand(tree, points, band_level);
  extract::SurfaceBand fine_band = extract::MarkSurfaceBand(tree, points, depth);
  band.occupied.clear();
  const double chord_bound = params.chord_error * core::Diagonal(core::BoundingBox(impl.cloud->positions));
  const absl::flat_hash_set<uint64_t> crease_cells = CellsNearSharpFits(impl, tree, band_level, depth, region);
  LSQSURF_RETURN_IF_ERROR(extract::RefineSurfaceBand(
      tree, band, band_level, fine_band,
      [&](const extract::OctreeCell& c) {
        if (crease_cells.contains(extract::CellKey(c))) return true;
        return extract::EstimateChordError(function, tree.CellCentre(c), tree.CellEdge(c.level)) > chord_bound;
      },
      ctx));
  band.ancestors.clear();
  fine_band.ancestors.clear();
  tree.Balance();
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  built->start.reserve(fine_band.occupied.size());
  for (uint64_t key : fine_band.occupied) built->start.push_back(extract::CellFromKey(key));
  return built;
}

// Adds the vertex attributes "depth", "degree" and "feature" (the dominant fit's) to `mesh`.
absl::Status LabelVertices(const PuFunction& function, core::TriangleMesh& mesh, core::JobContext& ctx) {
  core::ScalarAttribute depth_attribute{"depth", std::vector<float>(mesh.vertices.size())};
  core::ScalarAttribute degree_attribute{"degree", std::vector<float>(mesh.vertices.size())};
  core::ScalarAttribute feature_attribute{"feature", std::vector<float>(mesh.vertices.size())};
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      mesh.vertices.size(), 1024,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) {
          const FitLabel label = function.DominantFit(mesh.vertices[i].cast<double>());
          depth_attribute.values[i] = static_cast<float>(label.depth);
          degree_attribute.values[i] = static_cast<float>(label.degree);
          feature_attribute.values[i] = static_cast<float>(label.feature);
        }
      },
      &ctx));
  mesh.vertex_attributes.push_back(std::move(depth_attribute));
  mesh.vertex_attributes.push_back(std::move(degree_attribute));
  mesh.vertex_attributes.push_back(std::move(feature_attribute));
  return absl::OkStatus();
}

// The leaves of `tree` whose cube meets one of the balls: a descent from the root that carries the
// balls meeting each cell.
std::vector<extract::OctreeCell> LeavesMeetingBalls(const extract::AdaptiveOctree& tree,
                                                    std::span<const PuEditStats::Ball> balls) {
  auto meets = [&](const extract::OctreeCell& c, const PuEditStats::Ball& ball) {
    const double edge = tree.CellEdge(c.level);
    const Vec3d lo = tree.origin() + edge * Vec3d(c.x, c.y, c.z);
    const Vec3d nearest = ball.centre.cwiseMax(lo).cwiseMin(lo + Vec3d::Constant(edge));
    return (nearest - ball.centre).squaredNorm() <= ball.radius * ball.radius;
  };
  std::vector<extract::OctreeCell> leaves;
  std::vector<std::pair<extract::OctreeCell, std::vector<uint32_t>>> stack;
  std::vector<uint32_t> all(balls.size());
  for (uint32_t i = 0; i < all.size(); ++i) all[i] = i;
  stack.push_back({extract::OctreeCell{}, std::move(all)});
  while (!stack.empty()) {
    auto [cell, near] = std::move(stack.back());
    stack.pop_back();
    const extract::OctreeCell here = cell;  // Lambdas capture no structured binding before clang 16.
    std::erase_if(near, [&](uint32_t i) { return !meets(here, balls[i]); });
    if (near.empty()) continue;
    if (!tree.IsSubdivided(cell)) {
      if (tree.IsLeaf(cell)) leaves.push_back(cell);
      continue;
    }
    for (uint32_t k = 0; k < 8; ++k) {
      stack.push_back(
          {{cell.level + 1, 2 * cell.x + (k & 1), 2 * cell.y + ((k >> 1) & 1), 2 * cell.z + (k >> 2)}, near});
    }
  }
  return leaves;
}

bool SameExtraction(const PuExtractParams& a, const PuExtractParams& b) {
  const extract::MarchingOptions &x = a.marching, &y = b.marching;
  return a.cell_size == b.cell_size && a.chord_error == b.chord_error && a.label_vertices == b.label_vertices &&
         x.refine_steps == y.refine_steps && x.max_patch_triangles == y.max_patch_triangles &&
         x.crease_angle == y.crease_angle && x.snap_share == y.snap_share && x.relax_steps == y.relax_steps &&
         x.vertex_normals == y.vertex_normals;
}

// Only sharp fits make creases; without them there is nothing to split edges on.
extract::MarchingOptions MarchingFor(const PuFunction::Impl& impl, const PuExtractParams& params) {
  extract::MarchingOptions marching = params.marching;
  if (impl.sharp_fits.empty()) marching.crease_angle = 0;
  return marching;
}

}  // namespace

double FinestExtractionCell(const PuFunction& function, const PuExtractParams& params) {
  const double root_edge = function.stats().root_edge;
  return std::ldexp(root_edge, -ExtractionDepth(root_edge, params.cell_size * function.stats().mean_spacing));
}

absl::StatusOr<extract::IsosurfaceResult> Extract(const PuFunction& function, const PuExtractParams& params,
                                                  core::JobContext& ctx) {
  const PuFunction::Impl& impl = *function.impl_;
  core::SubContext build_ctx(ctx, "building the J1a tree", 0.0, 0.1);
  const auto tree_start = std::chrono::steady_clock::now();
  auto built = BuildExtractionTree(function, impl, params, nullptr, build_ctx);
  if (!built.ok()) return built.status();
  const double tree_seconds = core::SecondsSince(tree_start);
  core::SubContext extract_ctx(ctx, "extracting surface", 0.1, 0.95);
  auto result = extract::ExtractIsosurfaceOnTree(function, (*built)->tree, (*built)->start, params.max_leaves,
                                                 MarchingFor(impl, params), extract_ctx);
  built->reset();
  if (result.ok()) result->stats.tree_seconds = tree_seconds;
  if (!result.ok() || !params.label_vertices) return result;
  LSQSURF_RETURN_IF_ERROR(LabelVertices(function, result->mesh, ctx));
  return result;
}

absl::StatusOr<extract::IsosurfaceResult> ExtractEdited(const PuFunction& before, const PuFunction& after,
                                                        const PuEditStats& edit_stats, KeptSurface kept,
                                                        const PuExtractParams& requested, core::JobContext& ctx) {
  const PuExtractParams& params = kept.params;
  if (!SameExtraction(params, requested)) {
    return absl::FailedPreconditionError("the kept surface was extracted with other parameters");
  }
  // A snapped corner's place depends on every tetrahedron around it, some beyond the patch.
  if (params.marching.snap_share > 0) {
    return absl::FailedPreconditionError("a kept surface with snapped corners is extracted whole");
  }
  const PuFunction::Impl& b = *before.impl_;
  if (edit_stats.changed.empty()) return absl::FailedPreconditionError("the edit names no changed region");
  const auto tree_start = std::chrono::steady_clock::now();
  const auto levels = LevelsFor(before, params);
  if (!levels.ok()) return levels.status();
  const double coarse_cell = std::ldexp(b.root_edge, -levels->band);
  core::Box3 changed;
  for (const PuEditStats::Ball& ball : edit_stats.changed) {
    changed.extend(ball.centre - Vec3d::Constant(ball.radius));
    changed.extend(ball.centre + Vec3d::Constant(ball.radius));
  }
  // Balancing and the band's neighbours reach about two coarse cells; four keep the tree exact.
  const Vec3d margin = Vec3d::Constant(4 * coarse_cell);
  const core::Box3 region(changed.min() - margin, changed.max() + margin);
  core::SubContext build_ctx(ctx, "building the J1a tree near the edit", 0.0, 0.2);
  auto built = BuildExtractionTree(before, b, params, &region, build_ctx);
  if (!built.ok()) return built.status();
  const extract::AdaptiveOctree& tree = (*built)->tree;
  std::vector<extract::OctreeCell> leaves = LeavesMeetingBalls(tree, edit_stats.changed);
  absl::flat_hash_set<uint64_t> cells;
  for (const extract::OctreeCell& c : leaves) cells.insert(extract::CellKey(c));
  // Every kept face near the change must come from a leaf of this tree (else the tree is not the
  // one the kept surface was made on, and the join would not be exact).
  for (uint64_t key : kept.trace.face_cells) {
    if (cells.contains(key)) continue;
    const extract::OctreeCell c = extract::CellFromKey(key);
    const Vec3d centre = tree.CellCentre(c);
    if (changed.contains(centre) && !tree.IsLeaf(c)) {
      return absl::FailedPreconditionError("the kept surface was made on another tree");
    }
  }
  const double tree_seconds = core::SecondsSince(tree_start);
  core::SubContext march_ctx(ctx, "extracting the edited part", 0.2, 0.8);
  const extract::MarchingOptions marching = MarchingFor(*after.impl_, params);
  auto patch = extract::MarchLeaves(after, tree, leaves, marching, march_ctx);
  if (!patch.ok()) return patch.status();
  built->reset();
  auto join = extract::PatchJoin::Prepare(kept.mesh, kept.trace, cells, *patch);
  if (!join.ok()) return join.status();
  core::SubContext finish_ctx(ctx, "finishing the edited part", 0.8, 0.95);
  LSQSURF_RETURN_IF_ERROR(extract::internal::FinishSurface(after, marching, *patch, finish_ctx, join->fixed()));
  if (!kept.mesh.vertex_attributes.empty()) LSQSURF_RETURN_IF_ERROR(LabelVertices(after, patch->mesh, ctx));
  extract::IsosurfaceResult result;
  result.stats = patch->stats;
  result.stats.tree_seconds = tree_seconds;
  result.stats.replaced_faces = join->removed_faces();
  result.stats.seam_edges = join->seam_edges();
  result.mesh = join->Merge(std::move(kept.mesh), std::move(kept.trace), *patch, result.trace);
  return result;
}

std::span<const Vec3f> PuFunction::points() const { return impl_->cloud->positions; }

core::FieldGradient PuFunction::ValueOrDataSide(const Vec3d& x, bool with_gradient) const {
  const Impl& m = *impl_;
  const core::Neighbor nearest = m.cloud->kd_tree->Nearest(x.cast<float>());
  const double reach = m.coverage_check ? m.coverage_factor * m.cloud->local_spacing[nearest.index] : 0;
  if (!m.coverage_check || nearest.distance2 <= reach * reach) {
    core::FieldGradient g = m.Evaluate(x, with_gradient, false);
    g.defined = std::isfinite(g.value);
    return g;
  }
  const Vec3d d = x - m.cloud->positions[nearest.index].cast<double>();
  const double side = d.dot(m.cloud->normals[nearest.index].cast<double>()) >= 0 ? 1.0 : -1.0;
  const double length = d.norm();
  core::FieldGradient g;
  g.value = side * length;
  if (with_gradient && length > 0) g.gradient = side * d / length;
  return g;
}

bool PuFunction::NearCrease(const Vec3d& x) const {
  bool crease = false;
  impl_->ForEachSupport(x, [&](const LocalFit& fit, double) { crease |= fit.feature != Feature::kSmooth; });
  return crease;
}

namespace {

constexpr std::string_view kPuMagic = "LQPU0002";

// Structure checks of a read function: every index in range, so that evaluation cannot leave
// its arrays whatever the bytes were.
bool Consistent(const PuFunction::Impl& m) {
  const size_t nodes = m.nodes.size();
  if (nodes == 0 || m.fits.empty() || !(m.root_edge > 0) || !m.origin.allFinite()) return false;
  if (m.cloud->normals.size() != m.cloud->positions.size()) return false;
  if (m.coverage_check && m.cloud->local_spacing.size() != m.cloud->positions.size()) return false;
  for (size_t i = 0; i < nodes; ++i) {
    const Node& n = m.nodes[i];
    if (n.level < 0 || n.level > 30) return false;
    if (n.first_child >= 0 &&
        (static_cast<size_t>(n.first_child) <= i || static_cast<size_t>(n.first_child) + 8 > nodes))
      return false;
    if (n.fit >= 0 && static_cast<size_t>(n.fit) >= m.fits.size()) return false;
  }
  for (const LocalFit& f : m.fits) {
    const int highest = f.quadric ? kQuadricLabel : kMaxDegree;
    if (f.degree < 0 || f.degree > highest || !(f.support_radius > 0) || !(f.scale > 0)) return false;
    if (f.sharp >= 0 && static_cast<size_t>(f.sharp) >= m.sharp_fits.size()) return false;
  }
  for (const SharpFit& f : m.sharp_fits) {
    if (f.count < 2 || f.count > 4) return false;
    // Read as bytes: a stored flag other than 0 or 1 is not a bool.
    std::array<uint8_t, sizeof(f.take_max)> flags;
    std::memcpy(flags.data(), f.take_max.data(), sizeof(f.take_max));
    for (uint8_t flag : flags) {
      if (flag > 1) return false;
    }
    for (int k = 0; k < f.count; ++k) {
      if (f.sheets[static_cast<size_t>(k)].height.degree < 0 || f.sheets[static_cast<size_t>(k)].height.degree > 2)
        return false;
    }
  }
  return true;
}

// A fit as bytes: its frame and only the coefficients its degree uses (most fits are of degree
// 1–2, so this stores about half of the fixed-size record).
int StoredTerms(const LocalFit& f) { return f.quadric ? 10 : TermCount(f.degree); }

void WriteFits(std::span<const LocalFit> fits, core::BinaryWriter& w) {
  w.Scalar<uint64_t>(fits.size());
  for (const LocalFit& f : fits) {
    for (const Vec3d* v : {&f.centre, &f.origin, &f.tangent_u, &f.tangent_v, &f.normal}) {
      w.Scalar(v->x()), w.Scalar(v->y()), w.Scalar(v->z());
    }
    w.Scalar(f.support_radius), w.Scalar(f.scale);
    w.Scalar(f.degree), w.Scalar(f.depth), w.Scalar<uint8_t>(f.quadric), w.Scalar(f.feature), w.Scalar(f.sharp);
    const int terms = std::clamp(StoredTerms(f), 0, kMaxTerms);
    for (int k = 0; k < terms; ++k) w.Scalar(f.coefficients[static_cast<size_t>(k)]);
  }
}

bool ReadFits(core::BinaryReader& r, std::vector<LocalFit>& fits) {
  uint64_t count = 0;
  if (!r.Scalar(count) || count > (uint64_t{1} << 32)) return false;
  fits.clear();
  fits.reserve(static_cast<size_t>(std::min<uint64_t>(count, 1 << 24)));
  for (uint64_t i = 0; i < count; ++i) {
    LocalFit f;
    for (Vec3d* v : {&f.centre, &f.origin, &f.tangent_u, &f.tangent_v, &f.normal}) {
      if (!r.Scalar(v->x()) || !r.Scalar(v->y()) || !r.Scalar(v->z())) return false;
    }
    uint8_t quadric = 0;
    if (!r.Scalar(f.support_radius) || !r.Scalar(f.scale) || !r.Scalar(f.degree) || !r.Scalar(f.depth) ||
        !r.Scalar(quadric) || !r.Scalar(f.feature) || !r.Scalar(f.sharp)) {
      return false;
    }
    f.quadric = quadric != 0;
    const int terms = StoredTerms(f);
    if (terms < 0 || terms > kMaxTerms) return false;
    for (int k = 0; k < terms; ++k) {
      if (!r.Scalar(f.coefficients[static_cast<size_t>(k)])) return false;
    }
    fits.push_back(f);
  }
  return true;
}

}  // namespace

std::string SerializePu(const PuFunction& function) {
  const PuFunction::Impl& m = *function.impl_;
  const PuStats& st = function.stats_;
  core::BinaryWriter w;
  w.Array<char>(std::span<const char>(kPuMagic.data(), kPuMagic.size()));
  w.Scalar(m.params);
  w.Scalar<uint8_t>(m.coverage_check);
  w.Scalar(m.coverage_factor);
  w.Scalar(m.origin.x()), w.Scalar(m.origin.y()), w.Scalar(m.origin.z());
  w.Scalar(m.root_edge);
  w.Scalar(m.deepest_level);
  for (double v : {st.root_edge, st.mean_spacing, st.noise_estimate, st.error_threshold}) w.Scalar(v);
  w.Scalar(st.min_points);
  w.Array<Vec3f>(m.cloud->positions);
  w.Array<Vec3f>(m.cloud->normals);
  w.Array<float>(m.cloud->local_spacing);
  w.Array<Node>(m.nodes);
  WriteFits(m.fits, w);
  w.Array<SharpFit>(m.sharp_fits);
  return w.Take();
}

bool IsStoredPu(std::string_view bytes) {
  return bytes.size() >= 8 + kPuMagic.size() && bytes.substr(8, kPuMagic.size()) == kPuMagic;
}

absl::StatusOr<std::unique_ptr<PuFunction>> DeserializePu(std::string_view bytes) {
  auto bad = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("the stored PU function is unreadable: ", why));
  };
  core::BinaryReader r(bytes);
  std::vector<char> magic;
  if (!r.Array(magic) || std::string_view(magic.data(), magic.size()) != kPuMagic) return bad("wrong header");
  std::unique_ptr<PuFunction> function(new PuFunction());
  PuFunction::Impl& m = *function->impl_;
  PuStats& st = function->stats_;
  uint8_t coverage = 0;
  if (!r.Scalar(m.params) || !r.Scalar(coverage) || !r.Scalar(m.coverage_factor) || !r.Scalar(m.origin.x()) ||
      !r.Scalar(m.origin.y()) || !r.Scalar(m.origin.z()) || !r.Scalar(m.root_edge) || !r.Scalar(m.deepest_level) ||
      !r.Scalar(st.root_edge) || !r.Scalar(st.mean_spacing) || !r.Scalar(st.noise_estimate) ||
      !r.Scalar(st.error_threshold) || !r.Scalar(st.min_points)) {
    return bad("header fields");
  }
  m.coverage_check = coverage != 0;
  if (!r.Array(m.cloud->positions) || m.cloud->positions.size() < 4 ||
      !r.Array(m.cloud->normals, m.cloud->positions.size()) || !r.Array(m.cloud->local_spacing)) {
    return bad("points");
  }
  if (!r.Array(m.nodes) || !ReadFits(r, m.fits) || !r.Array(m.sharp_fits) || !r.AtEnd()) return bad("fits");
  if (!Consistent(m)) return bad("inconsistent structure");
  m.cloud->kd_tree = std::make_unique<core::KdTree>(m.cloud->positions);
  core::LocalJobContext ctx;
  LSQSURF_RETURN_IF_ERROR(IndexInfluence(m, ctx));
  return function;
}

namespace {

// Drops the fits no leaf refers to, keeping the others in their order (so that the support
// lists of untouched leaves, sorted by index, sum in the same order as before). Returns the
// renumbering (old index → new, −1 for a dropped fit), empty when no fit is dropped.
std::vector<int32_t> CompactFits(PuFunction::Impl& m) {
  std::vector<int32_t> new_index(m.fits.size(), -1);
  for (const Node& n : m.nodes) {
    if (n.fit >= 0 && n.first_child < 0) new_index[static_cast<size_t>(n.fit)] = 0;
  }
  if (std::find(new_index.begin(), new_index.end(), -1) == new_index.end()) return {};
  std::vector<LocalFit> kept;
  for (size_t f = 0; f < m.fits.size(); ++f) {
    if (new_index[f] < 0) continue;
    new_index[f] = static_cast<int32_t>(kept.size());
    kept.push_back(m.fits[f]);
  }
  for (Node& n : m.nodes) {
    if (n.fit >= 0) n.fit = n.first_child < 0 ? new_index[static_cast<size_t>(n.fit)] : -1;
  }
  m.fits = std::move(kept);
  return new_index;
}

absl::Status CheckEdit(const PuEdit& edit) {
  if (!edit.centre.allFinite() || !(edit.radius > 0) || !std::isfinite(edit.radius)) {
    return absl::InvalidArgumentError("the edit needs a ball: a finite centre and a positive radius");
  }
  if (edit.action == PuEditAction::kSetDegree && (edit.degree < 0 || edit.degree > kMaxDegree)) {
    return absl::InvalidArgumentError(core::StrCat("degree ", edit.degree, " must be within [0, ", kMaxDegree, "]"));
  }
  if (edit.action == PuEditAction::kRefit && !(edit.error_threshold >= 1e-6 && edit.error_threshold <= 0.1)) {
    return absl::InvalidArgumentError(
        core::StrCat("error_threshold ", edit.error_threshold, " must be within [1e-06, 0.1]"));
  }
  return absl::OkStatus();
}

// The indices of the points inside a node's cube (the split rule's half-open octants).
void PointsInCube(const PuFunction::Impl& m, const Node& n, std::vector<core::Neighbor>& scratch,
                  std::vector<uint32_t>& out) {
  const double edge = m.Edge(n.level);
  const Vec3d lo = m.origin + Vec3d(n.x, n.y, n.z) * edge, hi = lo + Vec3d::Constant(edge);
  m.cloud->kd_tree->Radius(((lo + hi) / 2).cast<float>(), static_cast<float>(edge * kSqrt3 / 2 * 1.001), scratch);
  for (const core::Neighbor& p : scratch) {
    const Vec3d x = m.cloud->positions[p.index].cast<double>();
    if ((x.array() >= lo.array()).all() && (x.array() < hi.array()).all()) out.push_back(p.index);
  }
}

// A remove edit's points: those outside the ball, with a point index of their own. The fits
// centred in the ball go; coverage changes where a removed point was the nearest.
absl::Status RemovePoints(const PuFunction::Impl& b, PuFunction::Impl& m, const PuEdit& edit,
                          std::span<const int32_t> touched, PuEditStats& local) {
  m.cloud = std::make_shared<PointData>();
  const double r2 = edit.radius * edit.radius;
  double removed_spacing = 0;
  for (size_t i = 0; i < b.cloud->positions.size(); ++i) {
    if ((b.cloud->positions[i].cast<double>() - edit.centre).squaredNorm() < r2) {
      ++local.points_removed;
      if (!b.cloud->local_spacing.empty())
        removed_spacing = std::max<double>(removed_spacing, b.cloud->local_spacing[i]);
      continue;
    }
    m.cloud->positions.push_back(b.cloud->positions[i]);
    m.cloud->normals.push_back(b.cloud->normals[i]);
    if (!b.cloud->local_spacing.empty()) m.cloud->local_spacing.push_back(b.cloud->local_spacing[i]);
  }
  if (m.cloud->positions.size() < 4) return absl::FailedPreconditionError("the ball holds nearly every point");
  if (m.coverage_check) local.changed.push_back({edit.centre, edit.radius + m.coverage_factor * removed_spacing});
  for (int32_t node : touched) {
    Node& n = m.nodes[static_cast<size_t>(node)];
    if ((m.fits[static_cast<size_t>(n.fit)].centre - edit.centre).norm() < edit.radius) n.fit = -1;
  }
  m.cloud->kd_tree = std::make_unique<core::KdTree>(m.cloud->positions);
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::unique_ptr<PuFunction>> EditPu(const PuFunction& base, const PuEdit& edit, core::JobContext& ctx,
                                                   PuEditStats* stats) {
  LSQSURF_RETURN_IF_ERROR(CheckEdit(edit));
  const PuFunction::Impl& b = *base.impl_;
  std::unique_ptr<PuFunction> out(new PuFunction());
  PuFunction::Impl& m = *out->impl_;
  out->stats_ = base.stats_;
  m.params = b.params, m.origin = b.origin, m.root_edge = b.root_edge, m.deepest_level = b.deepest_level;
  m.coverage_check = b.coverage_check, m.coverage_factor = b.coverage_factor;
  m.nodes = b.nodes, m.fits = b.fits, m.sharp_fits = b.sharp_fits;
  PuEditStats local;
  // The leaves whose fit's support meets the ball.
  std::vector<int32_t> touched;
  for (size_t i = 0; i < m.nodes.size(); ++i) {
    const Node& n = m.nodes[i];
    if (n.first_child >= 0 || n.fit < 0) continue;
    const LocalFit& f = m.fits[static_cast<size_t>(n.fit)];
    const double gap = (f.centre - edit.centre).norm();
    if (gap >= f.support_radius + edit.radius) continue;
    touched.push_back(static_cast<int32_t>(i));
    local.reach = std::max(local.reach, gap + f.support_radius);
    local.changed.push_back({f.centre, f.support_radius});
  }
  if (touched.empty()) return absl::FailedPreconditionError("no local fit meets the ball: nothing to edit there");
  local.fits_replaced = static_cast<int64_t>(touched.size());
  if (edit.action == PuEditAction::kRemove) {
    LSQSURF_RETURN_IF_ERROR(RemovePoints(b, m, edit, touched, local));
  } else {
    m.cloud = b.cloud;
  }
  const double diagonal = core::Diagonal(core::BoundingBox(m.cloud->positions));
  PuParams params = m.params;
  params.sharp = false;  // An edited region is made smooth; its creases stay where they were fitted.
  double bound = params.error_threshold * diagonal;
  if (edit.action == PuEditAction::kSetDegree) {
    params.max_degree = edit.degree;
    params.max_depth = 0;  // No cell splits: each keeps its place in the tree.
    bound = 0;             // The highest degree the points determine, up to `degree`.
  } else if (edit.action == PuEditAction::kRefit) {
    params.error_threshold = edit.error_threshold;
    bound = edit.error_threshold * diagonal;
  }
  const BuildContext bc(params, m, m.cloud->normals, bound);
  if (edit.action == PuEditAction::kSetDegree) {
    std::vector<CellOutcome> outcomes(touched.size());
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        touched.size(), 8,
        [&](size_t begin, size_t end) {
          thread_local Scratch scratch;
          for (size_t i = begin; i < end; ++i) {
            outcomes[i] = ProcessCell(bc, m.nodes[static_cast<size_t>(touched[i])], {}, 0, scratch);
          }
        },
        &ctx));
    for (size_t i = 0; i < touched.size(); ++i) {
      Node& n = m.nodes[static_cast<size_t>(touched[i])];
      if (!outcomes[i].has_fit) {
        n.fit = -1;
        continue;
      }
      outcomes[i].fit.sharp = -1;
      outcomes[i].fit.feature = Feature::kSmooth;
      m.fits[static_cast<size_t>(n.fit)] = outcomes[i].fit;
    }
  } else if (edit.action == PuEditAction::kRefit) {
    std::vector<uint32_t> order;
    std::vector<std::array<uint32_t, 2>> ranges(m.nodes.size(), {0, 0});
    std::vector<core::Neighbor> scratch;
    for (int32_t node : touched) {
      Node& n = m.nodes[static_cast<size_t>(node)];
      n.fit = -1;
      const auto begin = static_cast<uint32_t>(order.size());
      PointsInCube(m, n, scratch, order);
      ranges[static_cast<size_t>(node)] = {begin, static_cast<uint32_t>(order.size())};
    }
    PuStats grown;
    grown.leaves_per_depth.assign(static_cast<size_t>(params.max_depth) + 1, 0);
    grown.fits_per_depth.assign(static_cast<size_t>(params.max_depth) + 1, 0);
    LSQSURF_RETURN_IF_ERROR(GrowSubtrees(bc, m, order, ranges, touched, params.max_depth, grown, ctx));
  }
  const std::vector<int32_t> renumber = CompactFits(m);
  if (m.fits.empty()) return absl::FailedPreconditionError("the edit leaves no local fit");
  // The new fits' supports (a refit's may reach past the ones they replace).
  std::vector<int32_t> new_fits;
  std::vector<int32_t> stack(touched.begin(), touched.end());
  while (!stack.empty()) {
    const Node& n = m.nodes[static_cast<size_t>(stack.back())];
    stack.pop_back();
    if (n.first_child >= 0) {
      for (int32_t c = 0; c < 8; ++c) stack.push_back(n.first_child + c);
    } else if (n.fit >= 0) {
      const LocalFit& f = m.fits[static_cast<size_t>(n.fit)];
      new_fits.push_back(n.fit);
      local.changed.push_back({f.centre, f.support_radius});
      local.reach = std::max(local.reach, (f.centre - edit.centre).norm() + f.support_radius);
    }
  }
  LSQSURF_RETURN_IF_ERROR(UpdateInfluence(b, m, touched, new_fits, renumber, ctx));
  local.fits_after = static_cast<int64_t>(m.fits.size());
  if (stats != nullptr) *stats = local;
  return out;
}

namespace {

constexpr std::string_view kSurfaceMagic = "LQSF0001";

// The extraction parameters a kept surface records, field by field (no padding bytes stored).
void WriteExtractParams(const PuExtractParams& p, core::BinaryWriter& w) {
  w.Scalar(p.cell_size), w.Scalar(p.chord_error), w.Scalar(p.max_leaves), w.Scalar<uint8_t>(p.label_vertices);
  const extract::MarchingOptions& m = p.marching;
  w.Scalar(m.refine_steps), w.Scalar<uint8_t>(m.vertex_normals), w.Scalar(m.max_patch_triangles);
  w.Scalar(m.crease_angle), w.Scalar(m.snap_share), w.Scalar(m.relax_steps);
}

bool ReadExtractParams(core::BinaryReader& r, PuExtractParams& p) {
  uint8_t label = 0, normals = 0;
  extract::MarchingOptions& m = p.marching;
  const bool ok = r.Scalar(p.cell_size) && r.Scalar(p.chord_error) && r.Scalar(p.max_leaves) && r.Scalar(label) &&
                  r.Scalar(m.refine_steps) && r.Scalar(normals) && r.Scalar(m.max_patch_triangles) &&
                  r.Scalar(m.crease_angle) && r.Scalar(m.snap_share) && r.Scalar(m.relax_steps);
  p.label_vertices = label != 0;
  m.vertex_normals = normals != 0;
  return ok && label <= 1 && normals <= 1;
}

}  // namespace

std::string SerializeSurface(const core::TriangleMesh& mesh, const extract::SurfaceTrace& trace,
                             const PuExtractParams& params) {
  core::BinaryWriter w;
  w.Array<char>(std::span<const char>(kSurfaceMagic.data(), kSurfaceMagic.size()));
  WriteExtractParams(params, w);
  w.Array<Vec3f>(mesh.vertices);
  w.Array<Vec3f>(mesh.normals);
  w.Array<core::Triangle>(mesh.faces);
  w.Scalar<uint64_t>(mesh.vertex_attributes.size());
  for (const core::ScalarAttribute& a : mesh.vertex_attributes) {
    w.Text(a.name);
    w.Array<float>(a.values);
  }
  w.Array<uint64_t>(trace.vertex_edges);
  w.Array<uint64_t>(trace.face_cells);
  return w.Take();
}

absl::StatusOr<KeptSurface> DeserializeSurface(std::string_view bytes) {
  auto bad = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("the kept surface is unreadable: ", why));
  };
  core::BinaryReader r(bytes);
  std::vector<char> magic;
  if (!r.Array(magic) || std::string_view(magic.data(), magic.size()) != kSurfaceMagic) return bad("wrong header");
  KeptSurface surface;
  core::TriangleMesh& mesh = surface.mesh;
  if (!ReadExtractParams(r, surface.params)) return bad("parameters");
  uint64_t attributes = 0;
  if (!r.Array(mesh.vertices) || !r.Array(mesh.normals) || !r.Array(mesh.faces) || !r.Scalar(attributes) ||
      attributes > 16) {
    return bad("mesh");
  }
  const size_t n = mesh.vertices.size();
  if (!mesh.normals.empty() && mesh.normals.size() != n) return bad("normals");
  for (uint64_t k = 0; k < attributes; ++k) {
    core::ScalarAttribute a;
    if (!r.Text(a.name) || !r.Array(a.values, n)) return bad("attributes");
    mesh.vertex_attributes.push_back(std::move(a));
  }
  if (!r.Array(surface.trace.vertex_edges, n) || !r.Array(surface.trace.face_cells, mesh.faces.size()) || !r.AtEnd()) {
    return bad("trace");
  }
  for (const core::Triangle& t : mesh.faces) {
    if (t[0] >= n || t[1] >= n || t[2] >= n) return bad("a face index out of range");
  }
  return surface;
}

}  // namespace lsqsurf::pu
