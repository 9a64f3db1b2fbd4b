// iaMLS surfaces: Fasshauer & Zhang 2007; seed §4. See iamls.h for the formulas.
#include "worker/mls/iamls.h"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <numbers>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/mls/oriented_points.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;
using core::Vec3f;

// Sparse symmetric kernel matrix A_ki = Ψ_i(x_k) in CSR form (float values: the iteration
// needs ~1e-6 relative accuracy at most, and this halves the largest buffer).
struct KernelMatrix {
  std::vector<uint64_t> row_start;
  std::vector<uint32_t> column;
  std::vector<float> value;

  void Multiply(const std::vector<double>& in, std::vector<double>& out) const {
    const size_t n = row_start.size() - 1;
    out.assign(n, 0.0);
    (void)core::ParallelFor(n, 4096, [&](size_t begin, size_t end) {
      for (size_t k = begin; k < end; ++k) {
        double sum = 0;
        for (uint64_t e = row_start[k]; e < row_start[k + 1]; ++e) sum += value[e] * in[column[e]];
        out[k] = sum;
      }
    });
  }
};

}  // namespace

struct IamlsFunction::Impl {
  std::vector<Vec3f> positions;
  std::vector<Vec3f> normals;
  std::vector<float> coefficient;  // c_i
  std::unique_ptr<core::KdTree> tree;
  double inv_h2 = 0;          // 1 / h²
  double eps2 = 0;            // ε²
  double scale = 0;           // ε³ / π^{3/2}
  float radius = 0;           // Truncation radius, cutoff · h / ε.
  double min_kernel_sum = 0;  // ΣΨ below which F is not trusted.
  double fallback_scale = 0;  // Scale of the sign-only extension (a typical ΣΨ).
};

const core::ParamTable<IamlsParams>& IamlsParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<IamlsParams>();
    t->Real<&IamlsParams::epsilon>("epsilon", 0.05, 3, "", "kernel shape parameter; larger = more detail")
        .Integer<&IamlsParams::iterations>("iterations", 0, 20, "", "residual-correction iterations; more = closer fit")
        .Real<&IamlsParams::spacing>("spacing", 0, 1e30, "model units",
                                     "kernel spacing h; 0 = spacing_scale x mean nearest-neighbour distance")
        .Real<&IamlsParams::spacing_scale>("spacing_scale", 0.25, 8, "", "multiplier of the measured spacing")
        .Real<&IamlsParams::cutoff>("cutoff", 2, 8, "", "kernel truncation at epsilon*r = cutoff")
        .Real<&IamlsParams::min_weight>("min_weight", 0, 0.99, "",
                                        "ghost-sheet guard: no surface where the kernel sum is below this share of "
                                        "its mean at the samples");
    return t;
  }();
  return *table;
}

absl::Status Validate(const IamlsParams& p) { return IamlsParamTable().Validate(p); }

namespace {

// Where ΣΨ is too small to trust F (the kernel's negative lobe takes over at ~1.22 h/ε),
// the value falls back to a Gaussian-weighted mean of the samples' tangent-plane distances
// (an IMLS with a positive kernel: no negative lobe, so its sign is right on both sides of the
// data), scaled like F near the threshold. Only its sign is used there (to classify grid
// corners); the function reports it as undefined so that no surface is placed on it.
template <bool kGradient>
core::FieldGradient Evaluate(const IamlsFunction::Impl& m, const Vec3d& x) {
  thread_local std::vector<core::Neighbor> nn;
  m.tree->Radius(x.cast<float>(), m.radius, nn);
  core::FieldGradient out;
  if (nn.empty()) {
    out.value = std::numeric_limits<double>::quiet_NaN();
    return out;
  }
  double f = 0, w = 0, gauss = 0, gauss_distance = 0;
  Vec3d g = Vec3d::Zero(), gauss_normal = Vec3d::Zero();
  for (const core::Neighbor& q : nn) {
    const Vec3d d = x - m.positions[q.index].cast<double>();
    const Vec3d n = m.normals[q.index].cast<double>();
    const double s = m.eps2 * d.squaredNorm() * m.inv_h2;
    const double e = std::exp(-s);
    const double psi = (2.5 - s) * e;
    const double l = n.dot(d) - m.coefficient[q.index];
    w += psi;
    f += l * psi;
    gauss += e;
    gauss_distance += n.dot(d) * e;
    gauss_normal += n * e;
    if constexpr (kGradient) {
      // dΨ/dx = (s − 7/2) e^{−s} · 2 ε² d / h²
      g += n * psi + l * ((s - 3.5) * e * 2.0 * m.eps2 * m.inv_h2) * d;
    }
  }
  // Trust F only where the kernel sum is clearly positive: it changes sign ~1.22 h/ε off the
  // data, and F has spurious zeros (ghost sheets) where it does.
  out.defined = w * m.scale > m.min_kernel_sum;
  if (out.defined) {
    out.value = f * m.scale;
    out.gradient = g * m.scale;
  } else if (gauss > 0) {
    out.value = m.fallback_scale * gauss_distance / gauss;
    out.gradient = m.fallback_scale * gauss_normal / gauss;
  } else {
    out.value = std::numeric_limits<double>::quiet_NaN();  // Underflow: nothing is known.
  }
  return out;
}

// Kernel matrix rows and the right-hand side s_k = Σ_i ℓ_i(x_k) Ψ_i(x_k).
// Two passes (count, then fill) build the CSR arrays in place: at a million points the matrix
// holds ~140 million entries, and a per-row staging copy would double the peak.
absl::Status FillKernelMatrix(const IamlsFunction::Impl& impl, KernelMatrix& a, std::vector<double>& s,
                              core::SubContext& setup_ctx, core::JobContext& ctx) {
  const size_t n = impl.positions.size();
  a.row_start.assign(n + 1, 0);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 1024,
      [&](size_t begin, size_t end) {
        std::vector<core::Neighbor> nn;
        for (size_t k = begin; k < end; ++k) {
          impl.tree->Radius(impl.positions[k], impl.radius, nn);
          a.row_start[k + 1] = nn.size();
        }
      },
      &ctx, [&](double f) { setup_ctx.Report(0.2 + 0.3 * f); }));
  for (size_t k = 0; k < n; ++k) a.row_start[k + 1] += a.row_start[k];
  a.column.resize(a.row_start[n]);
  a.value.resize(a.row_start[n]);
  return core::ParallelFor(
      n, 1024,
      [&](size_t begin, size_t end) {
        std::vector<core::Neighbor> nn;
        for (size_t k = begin; k < end; ++k) {
          impl.tree->Radius(impl.positions[k], impl.radius, nn);
          const Vec3d xk = impl.positions[k].cast<double>();
          double sk = 0;
          uint64_t e = a.row_start[k];
          for (const core::Neighbor& q : nn) {
            const Vec3d d = xk - impl.positions[q.index].cast<double>();
            const double si = impl.eps2 * d.squaredNorm() * impl.inv_h2;
            const double psi = impl.scale * (2.5 - si) * std::exp(-si);
            a.column[e] = q.index;
            a.value[e++] = static_cast<float>(psi);
            sk += impl.normals[q.index].cast<double>().dot(d) * psi;
          }
          s[k] = sk;
        }
      },
      &ctx, [&](double f) { setup_ctx.Report(0.5 + 0.5 * f); });
}

// The largest eigenvalue of the symmetric kernel matrix, by 25 power steps.
absl::StatusOr<double> LargestEigenvalue(const KernelMatrix& a, core::JobContext& ctx) {
  const size_t n = a.row_start.size() - 1;
  std::vector<double> v(n), av;
  for (size_t k = 0; k < n; ++k) v[k] = 1.0 + 0.5 * std::sin(static_cast<double>(k));
  double lambda = 0;
  for (int step = 0; step < 25; ++step) {
    double norm = 0;
    for (double x : v) norm += x * x;
    norm = std::sqrt(norm);
    for (double& x : v) x /= norm;
    a.Multiply(v, av);
    lambda = 0;
    for (size_t k = 0; k < n; ++k) lambda += v[k] * av[k];
    v.swap(av);
    if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
  }
  return lambda;
}

}  // namespace

core::FieldValue IamlsFunction::Value(const Vec3d& x) const {
  const core::FieldGradient g = Evaluate<false>(*impl_, x);
  return {g.value, g.defined};
}

core::FieldGradient IamlsFunction::ValueAndGradient(const Vec3d& x) const { return Evaluate<true>(*impl_, x); }

absl::StatusOr<std::unique_ptr<IamlsFunction>> BuildIamls(const core::PointCloud& cloud, const IamlsParams& params,
                                                          core::JobContext& ctx) {
  if (absl::Status s = Validate(params); !s.ok()) return s;
  core::SubContext setup_ctx(ctx, "building iaMLS", 0.0, 0.4);
  auto points = IndexOrientedPoints(cloud, params.spacing, params.spacing_scale, "iaMLS");
  if (!points.ok()) return points.status();
  auto impl = std::make_shared<IamlsFunction::Impl>();
  impl->positions = std::move(points->positions);
  impl->normals = std::move(points->normals);
  impl->tree = std::move(points->tree);
  const double h = points->spacing;
  const double eps = params.epsilon;
  impl->inv_h2 = 1.0 / (h * h);
  impl->eps2 = eps * eps;
  impl->scale = eps * eps * eps / std::pow(std::numbers::pi, 1.5);
  impl->radius = static_cast<float>(params.cutoff * h / eps);
  setup_ctx.Report(0.2);

  auto fn = std::unique_ptr<IamlsFunction>(new IamlsFunction());
  fn->h_ = h;
  fn->stats_.spacing = h;
  const size_t n = cloud.size();
  impl->coefficient.assign(n, 0.0f);
  {
    KernelMatrix a;
    std::vector<double> s(n);
    LSQSURF_RETURN_IF_ERROR(FillKernelMatrix(*impl, a, s, setup_ctx, ctx));
    fn->stats_.mean_neighbors = static_cast<double>(a.row_start[n]) / static_cast<double>(n);
    // ΣΨ at the samples sets the scale of "clearly positive" for the ghost-sheet guard.
    double weight_sum = 0;
    for (float v : a.value) weight_sum += v;
    fn->stats_.mean_sample_weight = weight_sum / static_cast<double>(n);
    impl->fallback_scale = fn->stats_.mean_sample_weight;
    impl->min_kernel_sum = params.min_weight * fn->stats_.mean_sample_weight;
    if (params.iterations == 0) {
      fn->impl_ = std::move(impl);
      return fn;
    }

    // Richardson iteration c ← c + (s − A c) converges iff the spectrum of the symmetric A lies
    // in (0, 2). Estimate its largest eigenvalue with a few power steps before iterating.
    core::SubContext iter_ctx(ctx, "iterating iaMLS", 0.4, 1.0);
    auto largest = LargestEigenvalue(a, ctx);
    if (!largest.ok()) return largest.status();
    const double lambda = *largest;
    fn->stats_.largest_eigenvalue = lambda;
    if (lambda >= 1.98) {
      // λ_max grows roughly like ε³ (the self term 2.5 ε³/π^{3/2} dominates); suggest an ε that
      // brings it to about 1.5.
      const double suggested = eps * std::cbrt(1.5 / lambda);
      return absl::InvalidArgumentError(
          fmt::format("epsilon={:.3g} makes the iaMLS iteration diverge on this cloud (largest eigenvalue of "
                      "the kernel matrix {:.3g}, must be below 2); use epsilon <= {:.2f} or iterations=0",
                      eps, lambda, suggested));
    }
    std::vector<double> c(n, 0.0), ac;
    for (int it = 0; it < params.iterations; ++it) {
      a.Multiply(c, ac);
      double max_residual = 0;
      for (size_t k = 0; k < n; ++k) {
        const double residual = s[k] - ac[k];  // F⁽ⁱᵗ⁾(x_k); the data value there is 0.
        max_residual = std::max(max_residual, std::abs(residual));
        c[k] += residual;
      }
      fn->stats_.residuals.push_back(max_residual / h);
      iter_ctx.Report(static_cast<double>(it + 1) / params.iterations);
      if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
    }
    a.Multiply(c, ac);
    double max_residual = 0;
    for (size_t k = 0; k < n; ++k) max_residual = std::max(max_residual, std::abs(s[k] - ac[k]));
    fn->stats_.residuals.push_back(max_residual / h);
    for (size_t k = 0; k < n; ++k) impl->coefficient[k] = static_cast<float>(c[k]);
  }
  fn->impl_ = std::move(impl);
  return fn;
}

}  // namespace lsqsurf::mls
