#include "worker/mls/algebraic_mls.h"

#include <cmath>
#include <limits>

#include <Eigen/Cholesky>

#include "worker/core/kd_tree.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;
using core::Vec3f;

// Relative size below which S_pp − ‖S_p‖²/W counts as zero: the points are (nearly) coplanar
// seen from x, so the sphere's curvature is not determined and a plane is fitted instead.
constexpr double kFlatTolerance = 1e-10;

// An algebraic sphere u₀ + u_l·y + u₄‖y‖² in the scaled local frame of an evaluation point.
struct Sphere {
  double u0 = 0, u4 = 0;
  Vec3d ul = Vec3d::Zero();
};

struct Sums {
  double w = 0, pn = 0, pp = 0;
  Vec3d p = Vec3d::Zero(), n = Vec3d::Zero();
};

Sphere FitRamls(const Sums& s) {
  Sphere sphere;
  const double spread = s.pp - s.p.squaredNorm() / s.w;
  if (spread > kFlatTolerance * std::max(s.pp, s.p.squaredNorm() / s.w)) {
    sphere.u4 = 0.5 * (s.pn - s.p.dot(s.n) / s.w) / spread;
  }
  sphere.ul = (s.n - 2 * sphere.u4 * s.p) / s.w;
  sphere.u0 = -(sphere.ul.dot(s.p) + sphere.u4 * s.pp) / s.w;
  return sphere;
}

}  // namespace

struct AlgebraicMlsFunction::Impl {
  std::vector<Vec3f> positions, normals;
  std::unique_ptr<core::KdTree> kd_tree;
  AlgebraicMlsParams params;
  double h = 1, radius = 1;

  // F and the fitted sphere's gradient at x; `defined` as documented in the header. With
  // `facing`, only the points whose normal n has n·facing ≥ min_cosine enter the fit, in place of
  // the side rule of the parameters.
  core::FieldGradient Evaluate(const Vec3d& x, const Vec3f* facing = nullptr, float min_cosine = -1) const {
    thread_local std::vector<core::Neighbor> near;
    kd_tree->Radius(x.cast<float>(), static_cast<float>(radius), near);
    core::FieldGradient out;
    out.value = std::numeric_limits<double>::quiet_NaN();
    Sums s;
    Eigen::Matrix<double, 5, 5> normal_matrix = Eigen::Matrix<double, 5, 5>::Zero();
    Eigen::Matrix<double, 5, 1> rhs = Eigen::Matrix<double, 5, 1>::Zero();
    const bool apss = params.fit == AlgebraicFit::kApss;
    int weighted = 0;
    double nearest2 = std::numeric_limits<double>::infinity();
    // The side rule needs the nearest point's normal before the sums; without it the nearest
    // distance is tracked in the one pass.
    const bool one_side = facing != nullptr || params.side_cosine > -1;
    const double side_cosine = facing != nullptr ? min_cosine : params.side_cosine;
    Vec3f nearest_normal = facing != nullptr ? *facing : Vec3f::Zero();
    if (one_side && facing == nullptr) {
      for (const core::Neighbor& q : near) {
        if (q.distance2 < nearest2) {
          nearest2 = q.distance2;
          nearest_normal = normals[q.index];
        }
      }
    }
    const double r2 = radius * radius;
    for (const core::Neighbor& q : near) {
      const double d2 = q.distance2;
      if (d2 >= r2) continue;
      if (one_side && nearest_normal.dot(normals[q.index]) < side_cosine) continue;
      nearest2 = std::min(nearest2, d2);
      const double t = 1 - d2 / r2, w = t * t * t * t;
      const Vec3d y = (positions[q.index].cast<double>() - x) / radius;
      const Vec3d n = normals[q.index].cast<double>();
      ++weighted;
      s.w += w;
      s.p += w * y;
      s.n += w * n;
      s.pn += w * y.dot(n);
      s.pp += w * y.squaredNorm();
      if (apss) {
        Eigen::Matrix<double, 5, 1> row;
        row << 1, y.x(), y.y(), y.z(), y.squaredNorm();
        normal_matrix.selfadjointView<Eigen::Lower>().rankUpdate(row, w);
      }
    }
    if (!(s.w > 0)) return out;
    Sphere sphere;
    if (apss) {
      // The gradient rows [0, e_k, 2y_k] · u = n_k, summed over k, in closed form.
      const double bw = params.apss_beta;
      Eigen::Matrix<double, 5, 5> full = normal_matrix.selfadjointView<Eigen::Lower>();
      full.block<3, 3>(1, 1) += bw * s.w * Eigen::Matrix3d::Identity();
      full.block<3, 1>(1, 4) += 2 * bw * s.p;
      full.block<1, 3>(4, 1) += 2 * bw * s.p.transpose();
      full(4, 4) += 4 * bw * s.pp;
      rhs.segment<3>(1) = bw * s.n;
      rhs(4) = 2 * bw * s.pn;
      full.diagonal().array() += 1e-12 * full.trace();
      const Eigen::Matrix<double, 5, 1> u = full.ldlt().solve(rhs);
      sphere.u0 = u(0);
      sphere.ul = u.segment<3>(1);
      sphere.u4 = u(4);
    } else {
      sphere = FitRamls(s);
    }
    // Pratt normalization: ‖∇f‖ at the sphere's centre is √(‖u_l‖² − 4u₀u₄), so the value is
    // about a signed distance near the zero set (in units of R, hence the factor).
    const double pratt2 = sphere.ul.squaredNorm() - 4 * sphere.u0 * sphere.u4;
    const double scale = pratt2 > 0 ? std::sqrt(pratt2) : sphere.ul.norm();
    if (!(scale > 0)) return out;
    out.value = radius * sphere.u0 / scale;
    out.gradient = sphere.ul / scale;
    const double reach = params.coverage * h;
    out.defined = weighted >= params.min_neighbors && nearest2 <= reach * reach && std::isfinite(out.value);
    return out;
  }
};

absl::Status Validate(const AlgebraicMlsParams& p) {
  auto in = [](double v, double lo, double hi) { return std::isfinite(v) && v >= lo && v <= hi; };
  if (!(p.spacing == 0 || (std::isfinite(p.spacing) && p.spacing > 0))) {
    return absl::InvalidArgumentError("spacing must be 0 (measure it) or a positive length");
  }
  if (!in(p.spacing_scale, 0.25, 8)) return absl::InvalidArgumentError("spacing_scale must be in [0.25, 8]");
  if (!in(p.support_factor, 1, 10)) return absl::InvalidArgumentError("support_factor must be in [1, 10]");
  if (p.min_neighbors < 4 || p.min_neighbors > 100) return absl::InvalidArgumentError("min_neighbors must be in [4, 100]");
  if (!in(p.coverage, 0.25, 10)) return absl::InvalidArgumentError("coverage must be in [0.25, 10]");
  if (!in(p.side_cosine, -1, 1)) return absl::InvalidArgumentError("side_cosine must be in [-1, 1]");
  if (p.fit == AlgebraicFit::kApss && !(in(p.apss_beta, 0, 1e12) && p.apss_beta > 0)) {
    return absl::InvalidArgumentError("APSS beta must be in (0, 1e12]: without the normal term the fit is the zero polynomial");
  }
  return absl::OkStatus();
}

AlgebraicMlsFunction::AlgebraicMlsFunction() : impl_(std::make_unique<Impl>()) {}
AlgebraicMlsFunction::~AlgebraicMlsFunction() = default;

double AlgebraicMlsFunction::support_radius() const { return impl_->radius; }

core::FieldValue AlgebraicMlsFunction::Value(const Vec3d& x) const {
  const core::FieldGradient g = impl_->Evaluate(x);
  return {g.value, g.defined};
}

double AlgebraicMlsFunction::ValueOnly(const Vec3d& x) const { return impl_->Evaluate(x).value; }

core::FieldGradient AlgebraicMlsFunction::ValueAndGradient(const Vec3d& x) const { return impl_->Evaluate(x); }

core::FieldGradient AlgebraicMlsFunction::ValueAndGradientFacing(const Vec3d& x, const Vec3d& facing,
                                                                 double min_cosine) const {
  const Vec3f unit = facing.normalized().cast<float>();
  return impl_->Evaluate(x, &unit, static_cast<float>(min_cosine));
}

absl::StatusOr<std::unique_ptr<AlgebraicMlsFunction>> BuildAlgebraicMls(const core::PointCloud& cloud,
                                                                       const AlgebraicMlsParams& params,
                                                                       core::JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (!cloud.has_normals()) return absl::InvalidArgumentError("algebraic MLS surfaces need oriented normals");
  if (cloud.size() < 4) return absl::InvalidArgumentError("algebraic MLS surfaces need at least 4 points");
  for (size_t i = 0; i < cloud.size(); ++i) {
    if (!cloud.positions[i].allFinite() || !cloud.normals[i].allFinite()) {
      return absl::InvalidArgumentError(core::StrCat("point ", i, " has a non-finite position or normal"));
    }
  }
  std::unique_ptr<AlgebraicMlsFunction> function(new AlgebraicMlsFunction());
  AlgebraicMlsFunction::Impl& impl = *function->impl_;
  impl.params = params;
  impl.positions = cloud.positions;
  impl.normals = cloud.normals;
  for (Vec3f& n : impl.normals) {
    const float length = n.norm();
    n = length > 0 ? Vec3f(n / length) : Vec3f::Zero();
  }
  impl.kd_tree = std::make_unique<core::KdTree>(impl.positions);
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  impl.h = params.spacing > 0 ? params.spacing : params.spacing_scale * core::MeanNearestNeighborDistance(*impl.kd_tree);
  if (!(impl.h > 0)) return absl::InvalidArgumentError("all points coincide: no spacing to size the support by");
  impl.radius = params.support_factor * impl.h;
  function->h_ = impl.h;
  return function;
}

}  // namespace lsqsurf::mls
