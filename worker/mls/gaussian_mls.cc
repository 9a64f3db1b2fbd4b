#include "worker/mls/gaussian_mls.h"

#include <Eigen/Core>
#include <cmath>
#include <limits>

#include "worker/core/status.h"
#include "worker/mls/oriented_points.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;

// Adamson–Alexa's n(x) is undefined where the weighted normals cancel to less than this share
// of their weight: between the two sides of a sheet thinner than σ the direction is noise.
constexpr double kMinNormalAgreement = 0.25;

}  // namespace

struct GaussianMlsFunction::Impl {
  OrientedPoints points;
  GaussianMlsParams params;
  double inv_sigma2 = 1;  // 1 / σ²
  float radius = 1;       // cutoff × σ

  // With local offsets r_i = x − p_i and weights w_i (∇w_i = −2 r_i w_i / σ²):
  //  Kolluri:        F = Σ w_i (r_i·n_i) / W,  ∇F = (Σ w_i n_i + Σ (r_i·n_i) ∇w_i − F Σ∇w_i) / W;
  //  Adamson–Alexa:  F = n·c with c = Σ w_i r_i / W = x − a(x) and n = m/‖m‖, m = Σ w_i n_i;
  //                  ∇F = J_cᵀ n + J_nᵀ c, J_c = I + (Σ r_i ∇w_iᵀ − c Σ∇w_iᵀ) / W,
  //                  J_n = (I − n nᵀ) (Σ n_i ∇w_iᵀ) / ‖m‖.
  template <bool kGradient>
  core::FieldGradient Evaluate(const Vec3d& x) const {
    thread_local std::vector<core::Neighbor> near;
    points.tree->Radius(x.cast<float>(), radius, near);
    core::FieldGradient out;
    out.value = std::numeric_limits<double>::quiet_NaN();
    double w_sum = 0, distance_sum = 0, nearest2 = std::numeric_limits<double>::infinity();
    Vec3d offset_sum = Vec3d::Zero(), normal_sum = Vec3d::Zero(), dw_sum = Vec3d::Zero();
    Vec3d distance_dw = Vec3d::Zero();  // Σ (r_i·n_i) ∇w_i
    Eigen::Matrix3d offset_dw = Eigen::Matrix3d::Zero(), normal_dw = Eigen::Matrix3d::Zero();
    for (const core::Neighbor& q : near) {
      const Vec3d r = x - points.positions[q.index].cast<double>();
      const Vec3d n = points.normals[q.index].cast<double>();
      const double d2 = r.squaredNorm();
      const double w = std::exp(-d2 * inv_sigma2);
      nearest2 = std::min(nearest2, d2);
      w_sum += w;
      distance_sum += w * r.dot(n);
      offset_sum += w * r;
      normal_sum += w * n;
      if constexpr (kGradient) {
        const Vec3d dw = (-2 * w * inv_sigma2) * r;
        dw_sum += dw;
        distance_dw += r.dot(n) * dw;
        offset_dw += r * dw.transpose();
        normal_dw += n * dw.transpose();
      }
    }
    if (!(w_sum > 0)) return out;  // No point within reach, or every weight underflowed.
    const double reach = params.coverage * points.spacing;
    out.defined = static_cast<int>(near.size()) >= params.min_neighbors && nearest2 <= reach * reach;
    if (params.fit == GaussianFit::kKolluri) {
      out.value = distance_sum / w_sum;
      if constexpr (kGradient) out.gradient = (normal_sum + distance_dw - out.value * dw_sum) / w_sum;
      return out;
    }
    const double m_norm = normal_sum.norm();
    if (!(m_norm > 0)) {
      out.defined = false;
      return out;
    }
    out.defined = out.defined && m_norm >= kMinNormalAgreement * w_sum;
    const Vec3d n = normal_sum / m_norm, c = offset_sum / w_sum;
    out.value = n.dot(c);
    if constexpr (kGradient) {
      const Eigen::Matrix3d jc = Eigen::Matrix3d::Identity() + (offset_dw - c * dw_sum.transpose()) / w_sum;
      const Eigen::Matrix3d jn = (Eigen::Matrix3d::Identity() - n * n.transpose()) * normal_dw / m_norm;
      out.gradient = jc.transpose() * n + jn.transpose() * c;
    }
    return out;
  }
};

const core::ParamTable<GaussianMlsParams>& GaussianMlsParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<GaussianMlsParams>();
    t->Real<&GaussianMlsParams::spacing>("spacing", 0, 1e30, "model units",
                                         "h; 0 = spacing_scale x mean nearest-neighbour distance")
        .Real<&GaussianMlsParams::spacing_scale>("spacing_scale", 0.25, 8, "", "multiplier of the measured spacing")
        .Real<&GaussianMlsParams::width>("width", 0.25, 4, "h",
                                         "width sigma of the Gaussian weights exp(-d^2/sigma^2); larger = smoother")
        .Real<&GaussianMlsParams::cutoff>("cutoff", 2, 6, "sigma", "points farther than this are ignored")
        .Integer<&GaussianMlsParams::min_neighbors>("min_neighbors", 3, 100, "points",
                                                    "no surface where fewer points lie within the cutoff")
        .Real<&GaussianMlsParams::coverage>("coverage", 0.25, 10, "h",
                                            "no surface farther than this from the nearest point");
    return t;
  }();
  return *table;
}

absl::Status Validate(const GaussianMlsParams& p) { return GaussianMlsParamTable().Validate(p); }

GaussianMlsFunction::GaussianMlsFunction(std::unique_ptr<Impl> impl)
    : impl_(std::move(impl)), h_(impl_->points.spacing) {}
GaussianMlsFunction::~GaussianMlsFunction() = default;

double GaussianMlsFunction::width() const { return 1 / std::sqrt(impl_->inv_sigma2); }

core::FieldValue GaussianMlsFunction::Value(const Vec3d& x) const {
  const core::FieldGradient g = impl_->Evaluate<false>(x);
  return {g.value, g.defined};
}

double GaussianMlsFunction::ValueOnly(const Vec3d& x) const { return impl_->Evaluate<false>(x).value; }

core::FieldGradient GaussianMlsFunction::ValueAndGradient(const Vec3d& x) const { return impl_->Evaluate<true>(x); }

absl::StatusOr<std::unique_ptr<GaussianMlsFunction>> BuildGaussianMls(const core::PointCloud& cloud,
                                                                      const GaussianMlsParams& params,
                                                                      core::JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  auto points = IndexOrientedPoints(cloud, params.spacing, params.spacing_scale,
                                    params.fit == GaussianFit::kKolluri ? "IMLS" : "the Adamson-Alexa surface");
  if (!points.ok()) return points.status();
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  auto built = std::make_unique<GaussianMlsFunction::Impl>();
  GaussianMlsFunction::Impl& impl = *built;
  impl.params = params;
  impl.points = *std::move(points);
  const double sigma = params.width * impl.points.spacing;
  impl.inv_sigma2 = 1 / (sigma * sigma);
  impl.radius = static_cast<float>(params.cutoff * sigma);
  return std::make_unique<GaussianMlsFunction>(std::move(built));
}

}  // namespace lsqsurf::mls
