#include "worker/mls/algebraic_mls.h"

#include <Eigen/Cholesky>
#include <array>
#include <cmath>
#include <limits>

#include "worker/core/kd_tree.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/mls/oriented_points.h"

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

// The weighted sums of one fit, and what decides whether its F is defined.
struct FitAccumulator {
  Sums s;
  Eigen::Matrix<double, 5, 5> normal_matrix = Eigen::Matrix<double, 5, 5>::Zero();  // APSS only.
  int weighted = 0;
  double nearest2 = std::numeric_limits<double>::infinity();

  void Add(const Vec3d& y, const Vec3d& n, double w, double d2, bool apss) {
    nearest2 = std::min(nearest2, d2);
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

  // F and the fitted sphere's gradient; `defined` as documented in the header.
  core::FieldGradient Finish(const AlgebraicMlsParams& params, double h, double radius) const {
    core::FieldGradient out;
    out.value = std::numeric_limits<double>::quiet_NaN();
    if (!(s.w > 0)) return out;
    Sphere sphere;
    if (params.fit == AlgebraicFit::kApss) {
      // The gradient rows [0, e_k, 2y_k] · u = n_k, summed over k, in closed form.
      const double bw = params.apss_beta;
      Eigen::Matrix<double, 5, 5> full = normal_matrix.selfadjointView<Eigen::Lower>();
      full.block<3, 3>(1, 1) += bw * s.w * Eigen::Matrix3d::Identity();
      full.block<3, 1>(1, 4) += 2 * bw * s.p;
      full.block<1, 3>(4, 1) += 2 * bw * s.p.transpose();
      full(4, 4) += 4 * bw * s.pp;
      Eigen::Matrix<double, 5, 1> rhs = Eigen::Matrix<double, 5, 1>::Zero();
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

}  // namespace

struct AlgebraicMlsFunction::Impl {
  OrientedPoints points;
  AlgebraicMlsParams params;
  double h = 1, radius = 1;

  // The index of the point nearest x among `near` (none: −1).
  int64_t Nearest(const std::vector<core::Neighbor>& near) const {
    double nearest2 = std::numeric_limits<double>::infinity();
    int64_t index = -1;
    for (const core::Neighbor& q : near) {
      if (q.distance2 < nearest2) {
        nearest2 = q.distance2;
        index = q.index;
      }
    }
    return index;
  }

  // Feeds every point of `near` within the support to one of the accumulators: `pick(normal)`
  // returns 0, 1 or −1 (skip).
  template <typename Pick>
  void Accumulate(const Vec3d& x, const std::vector<core::Neighbor>& near, Pick&& pick,
                  std::array<FitAccumulator*, 2> into) const {
    const double r2 = radius * radius;
    const bool apss = params.fit == AlgebraicFit::kApss;
    for (const core::Neighbor& q : near) {
      const double d2 = q.distance2;
      if (d2 >= r2) continue;
      const int group = pick(points.normals[q.index]);
      if (group < 0 || into[static_cast<size_t>(group)] == nullptr) continue;
      const double t = 1 - d2 / r2, w = t * t * t * t;
      into[static_cast<size_t>(group)]->Add((points.positions[q.index].cast<double>() - x) / radius,
                                            points.normals[q.index].cast<double>(), w, d2, apss);
    }
  }

  // F and the fitted sphere's gradient at x. With `facing`, only the points whose normal n has
  // n·facing ≥ min_cosine enter the fit, in place of the side rule of the parameters.
  core::FieldGradient Evaluate(const Vec3d& x, const Vec3f* facing = nullptr, float min_cosine = -1) const {
    thread_local std::vector<core::Neighbor> near;
    points.tree->Radius(x.cast<float>(), static_cast<float>(radius), near);
    const bool one_side = facing != nullptr || params.side_cosine > -1;
    const double side_cosine = facing != nullptr ? min_cosine : params.side_cosine;
    // The side rule needs the nearest point's normal before the sums.
    Vec3f reference = Vec3f::Zero();
    if (facing != nullptr) {
      reference = *facing;
    } else if (const int64_t nearest = one_side ? Nearest(near) : -1; nearest >= 0) {
      reference = points.normals[static_cast<size_t>(nearest)];
    }
    FitAccumulator fit;
    Accumulate(x, near, [&](const Vec3f& n) { return !one_side || reference.dot(n) >= side_cosine ? 0 : -1; },
               {&fit, nullptr});
    return fit.Finish(params, h, radius);
  }

  SidesAt EvaluateSides(const Vec3d& x) const {
    thread_local std::vector<core::Neighbor> near;
    points.tree->Radius(x.cast<float>(), static_cast<float>(radius), near);
    const int64_t nearest = Nearest(near);
    const Vec3f reference = nearest < 0 ? Vec3f::Zero() : points.normals[static_cast<size_t>(nearest)];
    const float side_cosine = static_cast<float>(params.side_cosine > -1 ? params.side_cosine : 0.0);
    FitAccumulator own, other;
    Accumulate(x, near, [&](const Vec3f& n) { return reference.dot(n) >= side_cosine ? 0 : 1; }, {&own, &other});
    SidesAt out;
    out.near = own.Finish(params, h, radius);
    out.far = other.Finish(params, h, radius);
    // The far fit only has to be well posed, not near x: a coverage cut would switch it on and
    // off where the near side's value is small.
    out.far.defined = other.weighted >= params.min_neighbors && std::isfinite(out.far.value);
    if (own.s.w > 0 && other.s.w > 0) {
      // The far side's weighted centroid seen from the nearest point: in front of its outward
      // normal (a gap between two fronts) or behind it (the two walls of a neck). Not from the
      // near side's centroid: on a thread a few h across, that lies near the axis.
      const Vec3d centroid = x + other.s.p / other.s.w * radius;
      out.far_in_front =
          (centroid - points.positions[static_cast<size_t>(nearest)].cast<double>()).dot(reference.cast<double>()) > 0;
    }
    return out;
  }
};

namespace {

core::ParamTable<AlgebraicMlsParams>* MakeAlgebraicTable(AlgebraicFit fit) {
  auto* t = new core::ParamTable<AlgebraicMlsParams>();
  t->Real<&AlgebraicMlsParams::spacing>("spacing", 0, 1e30, "model units",
                                        "h; 0 = spacing_scale x mean nearest-neighbour distance")
      .Real<&AlgebraicMlsParams::spacing_scale>("spacing_scale", 0.25, 8, "", "multiplier of the measured spacing")
      .Real<&AlgebraicMlsParams::support_factor>("support_factor", 1, 10, "h", "support radius")
      .Integer<&AlgebraicMlsParams::min_neighbors>("min_neighbors", 4, 100, "points",
                                                   "no surface where fewer points carry weight")
      .Real<&AlgebraicMlsParams::coverage>("coverage", 0.25, 10, "h",
                                           "no surface farther than this from the nearest point")
      .Real<&AlgebraicMlsParams::side_cosine>("side_cosine", -1, 1, "",
                                              "only points whose normal has at least this cosine with the nearest "
                                              "point's normal enter a fit; -1 keeps all, -0.5 fits each side of a "
                                              "thin sheet alone");
  if (fit == AlgebraicFit::kApss) {
    t->Real<&AlgebraicMlsParams::apss_beta>("beta", 1e-6, 1e12, "",
                                            "weight of the normal term against the position term (large = RAMLS)");
  }
  return t;
}

}  // namespace

const core::ParamTable<AlgebraicMlsParams>& AlgebraicMlsParamTable(AlgebraicFit fit) {
  static const auto* ramls = MakeAlgebraicTable(AlgebraicFit::kRamls);
  static const auto* apss = MakeAlgebraicTable(AlgebraicFit::kApss);
  return fit == AlgebraicFit::kApss ? *apss : *ramls;
}

absl::Status Validate(const AlgebraicMlsParams& p) { return AlgebraicMlsParamTable(p.fit).Validate(p); }

AlgebraicMlsFunction::AlgebraicMlsFunction(std::unique_ptr<Impl> impl) : impl_(std::move(impl)), h_(impl_->h) {}
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

SidesAt AlgebraicMlsFunction::Sides(const Vec3d& x) const { return impl_->EvaluateSides(x); }

absl::StatusOr<std::unique_ptr<AlgebraicMlsFunction>> BuildAlgebraicMls(const core::PointCloud& cloud,
                                                                        const AlgebraicMlsParams& params,
                                                                        core::JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  auto points = IndexOrientedPoints(cloud, params.spacing, params.spacing_scale, "an algebraic MLS surface");
  if (!points.ok()) return points.status();
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  auto built = std::make_unique<AlgebraicMlsFunction::Impl>();
  AlgebraicMlsFunction::Impl& impl = *built;
  impl.params = params;
  impl.points = *std::move(points);
  impl.h = impl.points.spacing;
  impl.radius = params.support_factor * impl.h;
  return std::make_unique<AlgebraicMlsFunction>(std::move(built));
}

}  // namespace lsqsurf::mls
