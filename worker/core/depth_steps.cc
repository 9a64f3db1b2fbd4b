#include "worker/core/depth_steps.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <vector>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::core {
namespace {

constexpr double kWithinOneDegree = 0.99985;  // cos 1°.
// A neighbourhood is exactly flat where its spread along the normal (or, for range steps, in
// distance from the eye) is below this share of its radius, plus what rounding positions to
// float leaves (kFloatRounding of their magnitude) and what a grid the coordinates were
// quantized to leaves (CoordinateQuantum: a Draco upload's 16 bits over the box).
constexpr double kExactSpread = 1e-4;
constexpr double kFloatRounding = 2e-7;
// Exactly flat neighbourhoods whose depths lie within this share of each other are on one level,
// which takes at least kLevelSamples of them (a step of a depth camera is at least 1e-3 of the depth).
constexpr double kSameLevel = 1e-4;
constexpr size_t kLevelSamples = 2;
// Gaps between adjacent levels within this share of a whole multiple of the step agree with it,
// and at least kStepAgreement of them do where the levels are a sensor's steps (the stepped
// views: all), not faces that happen to be square to one direction at unrelated depths.
constexpr double kGapTolerance = 0.15;
constexpr double kStepAgreement = 0.6;
// Points seen nearer than this cosine to square to the axis have no stable image position.
constexpr double kLeastAxisCosine = 0.1;

struct Signature {
  double exact_share = 0, family_share = 0;
  bool radial = false;
  Vec3d axis = Vec3d::UnitZ();  // Away from the sensor, through the cloud.
  std::vector<double> levels;   // Depths (along the axis, or ranges) of the levels, ascending.
};

// A sampled point's neighbourhood: whether it is exactly flat, square to its normal or at one range.
struct SampledNeighborhood {
  bool planar = false, at_one_range = false;
  Vec3d normal, centroid;
  double range = 0;
};

// The step of the grid the coordinates lie on, where they lie on one (nearly every gap between
// sorted distinct values of a sample a whole multiple of the least one), else 0.
double CoordinateQuantum(std::span<const Vec3f> points) {
  constexpr size_t kValues = 8192;
  constexpr double kOnGrid = 0.9, kMultipleTolerance = 0.05;
  const size_t stride = std::max<size_t>(1, points.size() / kValues);
  double quantum = 0;
  std::vector<float> values;
  for (int axis = 0; axis < 3; ++axis) {
    values.clear();
    for (size_t i = 0; i < points.size(); i += stride) values.push_back(points[i][axis]);
    std::ranges::sort(values);
    values.erase(std::unique(values.begin(), values.end()), values.end());
    if (values.size() < 16) continue;
    double least = std::numeric_limits<double>::infinity();
    for (size_t k = 1; k < values.size(); ++k) least = std::min(least, double{values[k]} - values[k - 1]);
    size_t multiples = 0;
    for (size_t k = 1; k < values.size(); ++k) {
      const double ratio = (double{values[k]} - values[k - 1]) / least;
      multiples += std::abs(ratio - std::round(ratio)) <= kMultipleTolerance;
    }
    if (static_cast<double>(multiples) >= kOnGrid * static_cast<double>(values.size() - 1)) {
      quantum = std::max(quantum, least);
    }
  }
  return quantum;
}

SampledNeighborhood Examine(const KdTree& tree, size_t i, const Vec3d& eye, double quantum,
                            const DepthStepParams& params, std::vector<Neighbor>& found) {
  const std::span<const Vec3f> points = tree.points();
  const Vec3d p = points[i].cast<double>();
  tree.Knn(points[i], static_cast<size_t>(params.neighbors), found);
  SampledNeighborhood s;
  if (found.size() < 4) return s;
  Vec3d sum = Vec3d::Zero();
  Eigen::Matrix3d outer = Eigen::Matrix3d::Zero();
  double range_sum = 0, range_squares = 0;
  for (const Neighbor& n : found) {
    const Vec3d q = points[n.index].cast<double>() - p;  // About p, against cancellation.
    sum += q;
    outer += q * q.transpose();
    const double range = (q + p - eye).norm() - (p - eye).norm();
    range_sum += range;
    range_squares += range * range;
  }
  const double count = static_cast<double>(found.size());
  const Eigen::Matrix3d covariance = outer / count - (sum / count) * (sum / count).transpose();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(covariance);
  const double allowed = kExactSpread * std::sqrt(static_cast<double>(found.back().distance2)) +
                         kFloatRounding * p.cwiseAbs().maxCoeff() + quantum;
  s.planar = std::sqrt(std::max(0.0, eig.eigenvalues()(0))) <= allowed;
  s.at_one_range =
      std::sqrt(std::max(0.0, range_squares / count - (range_sum / count) * (range_sum / count))) <= allowed;
  s.normal = eig.eigenvectors().col(0);
  s.centroid = p + sum / count;
  s.range = (p - eye).norm() + range_sum / count;
  return s;
}

// Clusters of nearly equal depths with kLevelSamples or more.
std::vector<double> Levels(std::vector<double> depths) {
  std::ranges::sort(depths);
  std::vector<double> levels;
  for (size_t begin = 0; begin < depths.size();) {
    size_t end = begin + 1;
    double sum = depths[begin];
    while (end < depths.size() && depths[end] - depths[begin] <= kSameLevel * depths[begin]) sum += depths[end++];
    if (end - begin >= kLevelSamples && depths[begin] > 0) levels.push_back(sum / static_cast<double>(end - begin));
    begin = end;
  }
  return levels;
}

Signature MeasureSignature(std::span<const Vec3f> points, const Vec3d& eye, const DepthStepParams& params) {
  const KdTree tree(points);
  const double quantum = CoordinateQuantum(points);
  const size_t stride = std::max<size_t>(1, points.size() / static_cast<size_t>(params.sample));
  std::vector<SampledNeighborhood> planar, at_one_range;
  std::vector<Neighbor> found;
  size_t sampled = 0;
  Vec3d mean_ray = Vec3d::Zero();
  for (size_t i = 0; i < points.size(); i += stride, ++sampled) {
    mean_ray += (points[i].cast<double>() - eye).normalized();
    const SampledNeighborhood s = Examine(tree, i, eye, quantum, params, found);
    if (s.planar) planar.push_back(s);
    if (s.at_one_range && !s.planar) at_one_range.push_back(s);
  }
  Signature s;
  if (sampled == 0) return s;
  mean_ray.normalize();
  std::vector<double> depths;
  if (at_one_range.size() > planar.size()) {  // Range steps: each is square to its line of sight.
    s.radial = true;
    s.axis = mean_ray;
    s.exact_share = static_cast<double>(at_one_range.size()) / static_cast<double>(sampled);
    s.family_share = 1;
    for (const SampledNeighborhood& n : at_one_range) depths.push_back(n.range);
  } else if (!planar.empty()) {
    s.exact_share = static_cast<double>(planar.size()) / static_cast<double>(sampled);
    Eigen::Matrix3d directions = Eigen::Matrix3d::Zero();
    for (const SampledNeighborhood& n : planar) directions += n.normal * n.normal.transpose();
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(directions);
    const Vec3d family = eig.eigenvectors().col(2);
    s.axis = family.dot(mean_ray) < 0 ? -family : family;
    size_t parallel = 0;
    for (const SampledNeighborhood& n : planar) {
      if (std::abs(n.normal.dot(family)) < kWithinOneDegree) continue;
      ++parallel;
      depths.push_back((n.centroid - eye).dot(s.axis));
    }
    s.family_share = static_cast<double>(parallel) / static_cast<double>(planar.size());
  }
  s.levels = Levels(std::move(depths));
  return s;
}

// The depth of each point from `eye` (along the axis, or its range), 0 where it lies behind.
std::vector<double> Depths(std::span<const Vec3f> points, const Vec3d& eye, const Signature& s) {
  std::vector<double> depth(points.size());
  for (size_t i = 0; i < points.size(); ++i) {
    const Vec3d r = points[i].cast<double>() - eye;
    depth[i] = s.radial ? r.norm() : std::max(0.0, r.dot(s.axis));
  }
  return depth;
}

// How the step grows with depth: constant in inverse depth (disparity steps) or constant in
// depth (range steps), whichever more gaps between adjacent levels agree with.
struct StepModel {
  bool in_inverse = true;
  double step = 0;       // Of 1 / depth, or of depth.
  double agreement = 0;  // Share of the gaps that whole multiples of `step` explain.
  // The step of 1 / depth at inverse depth `w`.
  double InverseStepAt(double w) const { return in_inverse ? step : step * w * w; }
};

// The step of `gaps` between adjacent sampled levels (a level the sample missed doubles a gap):
// the lower quartile gap refined to the median of each gap over its multiple of it; `agreeing`
// counts the gaps within kGapTolerance of a whole multiple.
double BaseStep(std::vector<double> gaps, double& agreeing) {
  std::ranges::sort(gaps);
  const double quartile = gaps[gaps.size() / 4];
  std::vector<double> bases;
  agreeing = 0;
  for (double g : gaps) {
    const double multiple = std::max(1.0, std::round(g / quartile));
    bases.push_back(g / multiple);
    agreeing += std::abs(g / quartile - multiple) <= kGapTolerance;
  }
  std::ranges::nth_element(bases, bases.begin() + static_cast<std::ptrdiff_t>(bases.size() / 2));
  return bases[bases.size() / 2];
}

StepModel FitStepModel(const std::vector<double>& levels) {
  std::vector<double> inverse_gaps, gaps;
  for (size_t j = 1; j < levels.size(); ++j) {
    inverse_gaps.push_back(1 / levels[j - 1] - 1 / levels[j]);
    gaps.push_back(levels[j] - levels[j - 1]);
  }
  double inverse_agreeing = 0, agreeing = 0;
  StepModel model;
  const double inverse_step = BaseStep(inverse_gaps, inverse_agreeing);
  const double step = BaseStep(gaps, agreeing);
  model.in_inverse = inverse_agreeing >= agreeing;
  model.step = model.in_inverse ? inverse_step : step;
  model.agreement = std::max(inverse_agreeing, agreeing) / static_cast<double>(gaps.size());
  return model;
}

// Each point moved along its ray onto the plane of inverse depth fitted around it in the image.
absl::StatusOr<size_t> MoveOffSteps(std::span<Vec3f> points, const Vec3d& eye, const Signature& s,
                                    const std::vector<double>& depth, const StepModel& model,
                                    const DepthStepParams& params, JobContext& ctx) {
  const Vec3d side = s.axis.unitOrthogonal(), other = s.axis.cross(side);
  std::vector<Vec3f> image(points.size());
  std::vector<char> in_view(points.size(), 0);
  for (size_t i = 0; i < points.size(); ++i) {
    const Vec3d r = points[i].cast<double>() - eye;
    const double along = r.dot(s.axis);
    in_view[i] = along > kLeastAxisCosine * r.norm() && depth[i] > 0;
    // Points out of view are kept far from the rest (and not moved).
    image[i] = in_view[i] ? Vec3f(static_cast<float>(r.dot(side) / along), static_cast<float>(r.dot(other) / along), 0)
                          : Vec3f(0, 0, 1e6f);
  }
  const KdTree image_tree(image);
  std::vector<float> scale(points.size(), 1.0f);
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      points.size(), 2048,
      [&](size_t begin, size_t end) {
        std::vector<Neighbor> found;
        for (size_t i = begin; i < end; ++i) {
          if (!in_view[i]) continue;
          const double w = 1 / depth[i], step = model.InverseStepAt(w);
          // A window within one level learns nothing; a wider one may reach across the next riser.
          for (size_t k = static_cast<size_t>(params.window); k <= static_cast<size_t>(params.widest_window); k *= 4) {
            image_tree.Knn(image[i], k, found);
            Eigen::Matrix3d normal_matrix = Eigen::Matrix3d::Zero();
            Eigen::Vector3d right_side = Eigen::Vector3d::Zero();
            size_t used = 0;
            double lowest = w, highest = w;
            for (const Neighbor& n : found) {
              if (!in_view[n.index]) continue;
              const double wj = 1 / depth[n.index];
              if (std::abs(wj - w) > params.window_steps * step) continue;
              const Eigen::Vector3d row(1.0, image[n.index].x() - image[i].x(), image[n.index].y() - image[i].y());
              normal_matrix += row * row.transpose();
              right_side += row * (wj - w);
              lowest = std::min(lowest, wj);
              highest = std::max(highest, wj);
              ++used;
            }
            if (highest - lowest < 0.5 * step) continue;
            const Eigen::LDLT<Eigen::Matrix3d> solver(normal_matrix);
            if (used < 6 || solver.info() != Eigen::Success || solver.rcond() < 1e-12) break;
            const double fitted = w + std::clamp(solver.solve(right_side)(0), -0.5 * step, 0.5 * step);
            // A range step larger than the point's own depth (a stray next to the sensor) would
            // move it past the eye or far behind the cloud: such a point stays.
            if (fitted > 0.5 * w) scale[i] = static_cast<float>(w / fitted);
            break;
          }
        }
      },
      &ctx));
  size_t moved = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    if (scale[i] == 1.0f) continue;
    const Vec3d r = points[i].cast<double>() - eye;
    points[i] = (eye + r * static_cast<double>(scale[i])).cast<float>();
    ++moved;
  }
  return moved;
}

// Share of the gaps between adjacent `levels`, measured as depths from a sensor `offset` farther
// along the axis than assumed, that whole multiples of one step in inverse depth explain.
double InverseStepAgreement(const std::vector<double>& levels, double offset) {
  std::vector<double> gaps;
  for (size_t j = 1; j < levels.size(); ++j) {
    if (!(levels[j - 1] - offset > 0)) return 0;
    gaps.push_back(1 / (levels[j - 1] - offset) - 1 / (levels[j] - offset));
  }
  double agreeing = 0;
  BaseStep(gaps, agreeing);
  return agreeing / static_cast<double>(gaps.size());
}

// Whether the levels' steps place a stereo sensor at the origin (disparity steps measured from
// it agree, and clearly better than from a sensor kSensorShift of the median depth nearer or
// farther). Steps constant in depth fit a sensor anywhere along the axis and place none.
bool SensorAtOrigin(const std::vector<double>& levels) {
  constexpr double kSensorShift = 0.3, kAgreement = 0.8, kMargin = 0.2;
  const double at_origin = InverseStepAgreement(levels, 0), shift = kSensorShift * levels[levels.size() / 2];
  return at_origin >= kAgreement &&
         at_origin >= std::max(InverseStepAgreement(levels, shift), InverseStepAgreement(levels, -shift)) + kMargin;
}

}  // namespace

absl::StatusOr<DepthStepResult> UndoDepthSteps(std::span<Vec3f> points, const std::optional<Vec3d>& known_eye,
                                               const DepthStepParams& params, JobContext& ctx) {
  if (params.sample < 16 || params.neighbors < 8 || params.window < 9 || params.widest_window < params.window ||
      params.levels < 2 || !(params.window_steps >= 1) || !(params.exact_share > 0 && params.exact_share <= 1) ||
      !(params.family_share > 0 && params.family_share <= 1)) {
    return absl::InvalidArgumentError("depth step parameters out of range");
  }
  if (known_eye && !known_eye->allFinite()) return absl::InvalidArgumentError("the sensor position is not finite");
  const Vec3d eye = known_eye.value_or(Vec3d::Zero());
  DepthStepResult result;
  if (points.size() < static_cast<size_t>(params.neighbors) * 4) return result;
  const Signature signature = MeasureSignature(points, eye, params);
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  result.exact_share = signature.exact_share;
  result.family_share = signature.family_share;
  result.radial = signature.radial;
  result.levels = signature.levels.size();
  if (signature.exact_share < params.exact_share || signature.family_share < params.family_share ||
      result.levels < static_cast<size_t>(params.levels)) {
    return result;
  }
  if (!known_eye && (signature.radial || !SensorAtOrigin(signature.levels))) return result;
  const StepModel model = FitStepModel(signature.levels);
  result.step_agreement = model.agreement;
  if (!(model.step > 0) || model.agreement < kStepAgreement) return result;
  result.found = true;
  result.eye_inferred = !known_eye;
  const double median_depth = signature.levels[signature.levels.size() / 2];
  result.step = model.in_inverse ? model.step * median_depth * median_depth : model.step;
  auto moved = MoveOffSteps(points, eye, signature, Depths(points, eye, signature), model, params, ctx);
  if (!moved.ok()) return moved.status();
  result.moved = *moved;
  return result;
}

}  // namespace lsqsurf::core
