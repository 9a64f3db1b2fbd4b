// iaMLS surfaces: Fasshauer & Zhang 2007; seed §4. See iamls.h for the formulas.
#include "worker/mls/iamls.h"

#include <fmt/format.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <numbers>

#include "worker/core/kd_tree.h"
#include "worker/core/kernel_matrix.h"
#include "worker/core/noise.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/mls/oriented_points.h"

namespace lsqsurf::mls {
namespace {

using core::Vec3d;
using core::Vec3f;

using core::KernelMatrix;

}  // namespace

struct IamlsFunction::Impl {
  std::vector<Vec3f> positions;
  std::vector<Vec3f> normals;
  std::vector<float> coefficient;  // c_i
  std::unique_ptr<core::KdTree> tree;
  double inv_h2 = 0;              // 1 / h²
  double eps2 = 0;                // ε²
  double scale = 0;               // ε³ / π^{3/2}
  float radius = 0;               // Truncation radius, cutoff · h / ε.
  double min_kernel_sum = 0;      // ΣΨ below which F is not trusted.
  double fallback_scale = 0;      // Scale of the sign-only extension (a typical ΣΨ).
  double inv_normal_sigma2 = 0;   // 1 / normal_sigma², 0 without the crease-keeping refit.
  double inv_facing_radius2 = 0;  // 1 / ρ², ρ the reach of the facing reference (FacingDirection).
  bool thin_walls = false;        // IamlsStats::thin_walls.
  // Per sample, set by the builder's kernel rows: kThin where a neighbour within the kernel faces
  // against it, kNearThin where it lies within the kernel of such a sample.
  static constexpr uint8_t kThin = 1, kNearThin = 2;
  std::vector<uint8_t> wall_marks;
};

const core::ParamTable<IamlsParams>& IamlsParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<IamlsParams>();
    t->Real<&IamlsParams::epsilon>("epsilon", 0.05, 3, "", "kernel shape parameter; larger = more detail")
        .Or(0, "chosen from the noise")
        .Integer<&IamlsParams::iterations>("iterations", 0, 20, "", "residual-correction iterations; more = closer fit")
        .Or(-1, "chosen from the noise")
        .Real<&IamlsParams::spacing>("spacing", 0, 1e30, "model units",
                                     "kernel spacing h; 0 = spacing_scale x mean nearest-neighbour distance")
        .Real<&IamlsParams::spacing_scale>("spacing_scale", 0.25, 8, "", "multiplier of the measured spacing")
        .Real<&IamlsParams::cutoff>("cutoff", 2, 8, "", "kernel truncation at epsilon*r = cutoff")
        .Or(0, "chosen from epsilon")
        .Real<&IamlsParams::min_weight>("min_weight", 0, 0.99, "",
                                        "ghost-sheet guard: no surface where the kernel sum is below this share of "
                                        "its mean at the samples")
        .Real<&IamlsParams::noise_level>("noise_level", 0, 0.1, "share of the diagonal",
                                         "noise sigma for the choice of epsilon, iterations and cutoff; 0 declares "
                                         "the data exact")
        .Or(-1, "estimated from the data")
        .Real<&IamlsParams::normal_sigma>("normal_sigma", 0.2, 2, "",
                                          "crease-keeping refit: samples whose normals differ from the local mean "
                                          "normal by much more than this weigh less")
        .Or(-1, "chosen from the noise: 0.5 when noisy, else off")
        .Or(0, "off")
        .Integer<&IamlsParams::thin_walls>("thin_walls", 0, 1, "",
                                           "1 keeps walls thinner than the kernel apart by fading out the samples "
                                           "facing against those nearest each point; 0 blends all samples")
        .Or(-1, "chosen from the noise: on when clean, off when noisy unless nearly all of the cloud is thin walls");
    return t;
  }();
  return *table;
}

IamlsChoice ChooseIamlsParameters(double noise_ratio) {
  // Below this ratio the estimate is the clouds' own curvature residual, not noise.
  constexpr double kNoisyRatio = 0.15;
  if (!(noise_ratio >= kNoisyRatio)) return {};
  return {std::max(0.3, 0.55 / (1 + noise_ratio / 1.5)), 1, 3, 0.5, false};
}

absl::Status Validate(const IamlsParams& p) { return IamlsParamTable().Validate(p); }

namespace {

// The neighbour list of the point being evaluated, one per thread (Evaluate fills it).
std::vector<core::Neighbor>& Neighbours() {
  thread_local std::vector<core::Neighbor> nn;
  return nn;
}
// Thin walls. Where the kernel reaches through a wall thinner than itself (a plate, a finger, the
// edge of a sharp wedge), the far side's samples blend in with normals facing the other way and
// their ℓ_i cancel the near side's: F's zero moves about h/ε off both faces, and the two sides
// merge or tear. So each evaluation first finds the side of the wall x is on: the mean normal of
// the samples that x lies in front of (ℓ_i(x) ≥ −ρ/4) near the nearest such one (weights
// (1 − (d² − d_min²)/(2ρ)²)², ρ about one sample spacing), or of all samples near the nearest
// when x is behind every one (inside the wall, where either side's F is negative, so the choice
// leaves no zero behind). Then it fades out the samples facing against that direction (weight 1
// down to an angle of 101°, 0 from 127°), as if the far side were not there. Counting only the samples x is in front of
// keeps a gap in one face's sampling from handing x to the other face. Nothing is faded where
// the normals disagree (|mean| below a third of its weight: x is beyond an edge); on a smooth
// surface wider than the kernel no sample faces that far away and every factor is 1.
// Returns the direction, or zero where nothing is faded.
constexpr double kFadeStart = -0.2, kFadeEnd = -0.6;  // Cosines to the facing direction.

// Whether two samples face against each other as the two faces of a thin wall do (their normals
// more than 101° apart): what marks a sample thin.
bool FacingAgainst(const Vec3f& a, const Vec3f& b) { return a.dot(b) < kFadeStart; }

Vec3f FacingDirection(const IamlsFunction::Impl& m, const Vec3d& x, const std::vector<core::Neighbor>& nn) {
  constexpr double kCoherence = 1.0 / 3.0, kReach2 = 4.0, kFrontTolerance = 0.25;
  const float behind = static_cast<float>(-kFrontTolerance / std::sqrt(m.inv_facing_radius2));
  const Vec3f xf = x.cast<float>();
  auto in_front = [&](uint32_t i) { return m.normals[i].dot(xf - m.positions[i]) >= behind; };
  // The nearest sample x is in front of, else (x behind all: inside) the nearest of all.
  float nearest2 = std::numeric_limits<float>::infinity(), nearest_front2 = nearest2;
  for (const core::Neighbor& q : nn) {
    nearest2 = std::min(nearest2, q.distance2);
    if (q.distance2 < nearest_front2 && in_front(q.index)) nearest_front2 = q.distance2;
  }
  const bool front_only = nearest_front2 < std::numeric_limits<float>::infinity();
  const float from2 = front_only ? nearest_front2 : nearest2;
  const float reach2 = static_cast<float>(kReach2 / m.inv_facing_radius2);
  Vec3f reference = Vec3f::Zero();
  float total = 0;
  for (const core::Neighbor& q : nn) {
    const float excess = q.distance2 - from2;
    if (excess < 0 || excess >= reach2 || (front_only && !in_front(q.index))) continue;
    const float falloff = 1 - excess / reach2, w = falloff * falloff;
    reference += w * m.normals[q.index];
    total += w;
  }
  const float length = reference.norm();
  return length > 0 && length >= kCoherence * total ? Vec3f(reference / length) : Vec3f::Zero();
}

// A sample's factor for the facing `direction` (FacingDirection).
[[gnu::always_inline]] inline double Fade(const Vec3d& normal, const Vec3f& direction) {
  const double cosine = normal.dot(direction.cast<double>());
  if (cosine >= kFadeStart) return 1.0;
  const double ramp = std::max(0.0, (cosine - kFadeEnd) / (kFadeStart - kFadeEnd));
  return ramp * ramp * (3 - 2 * ramp);
}

// Term and GradientTerm run once per neighbour of every evaluation; left out of line by the
// compiler they made the noisy bench runs 40 % slower, hence always_inline.
// Sample i's part of F at x: offset d = x − x_i, normal n, s = ε²|d|²/h², e = e^{−s} and
// ℓ = n·d − c_i; its kernel is Ψ = (2.5 − s) e.
struct SampleTerm {
  Vec3d d, n;
  double s, e, l;
};

[[gnu::always_inline]] inline SampleTerm Term(const IamlsFunction::Impl& m, const Vec3d& x, uint32_t i) {
  SampleTerm t;
  t.d = x - m.positions[i].cast<double>();
  t.n = m.normals[i].cast<double>();
  t.s = m.eps2 * t.d.squaredNorm() * m.inv_h2;
  t.e = std::exp(-t.s);
  t.l = t.n.dot(t.d) - m.coefficient[i];
  return t;
}

// ∇(ℓ Ψ) of one sample, its Ψ scaled by a weight held constant in x; dΨ/dx = (s − 7/2) e · 2ε² d / h².
[[gnu::always_inline]] inline Vec3d GradientTerm(const IamlsFunction::Impl& m, const SampleTerm& t, double weight) {
  return weight * (t.n * ((2.5 - t.s) * t.e) + t.l * ((t.s - 3.5) * t.e * 2.0 * m.eps2 * m.inv_h2) * t.d);
}

// The crease-keeping refit: F again with each sample's Ψ scaled by exp(−|n_i − n̄|²/σ_n²),
// rescaled to the plain kernel sum `w` so that F keeps its magnitude (its sign is that of the
// refit). The weights' own dependence on x is left out of the gradient, as robust MLS does.
// `facing` is the thin-wall direction (FacingDirection).
template <bool kGradient>
void Refit(const IamlsFunction::Impl& m, const Vec3d& x, const Vec3d& reference_normal, const Vec3f& facing, double w,
           double& f, Vec3d& g) {
  double f2 = 0, w2 = 0;
  Vec3d g2 = Vec3d::Zero();
  const bool fading = !facing.isZero();
  for (const core::Neighbor& q : Neighbours()) {
    const SampleTerm t = Term(m, x, q.index);
    double r = std::exp(-(t.n - reference_normal).squaredNorm() * m.inv_normal_sigma2);
    if (fading) r *= Fade(t.n, facing);
    const double psi = (2.5 - t.s) * t.e * r;
    w2 += psi;
    f2 += t.l * psi;
    if constexpr (kGradient) g2 += GradientTerm(m, t, r);
  }
  if (!(w2 > 0)) return;  // Every weight went to the other face: keep the plain blend.
  f = f2 * w / w2;
  if constexpr (kGradient) g = g2 * w / w2;
}

// The neighbour sums of one evaluation: F's, the kernel sum, the positive Gaussian's fallback
// and the refit's reference normal.
struct KernelSums {
  double f = 0, w = 0, gauss = 0, gauss_distance = 0, reference_weight = 0;
  Vec3d g = Vec3d::Zero(), gauss_normal = Vec3d::Zero(), reference_normal = Vec3d::Zero();
  bool faded = false;  // Some sample was faded (thin walls).
};

// Adds one sample's term to `sums`, its weight scaled by `fade`.
template <bool kGradient>
[[gnu::always_inline]] inline void AddTerm(const IamlsFunction::Impl& m, const SampleTerm& t, double fade, bool refit,
                                           KernelSums& sums) {
  const double e = t.e * fade;
  const double psi = (2.5 - t.s) * e;
  sums.w += psi;
  sums.f += t.l * psi;
  sums.gauss += e;
  sums.gauss_distance += t.n.dot(t.d) * e;
  sums.gauss_normal += t.n * e;
  // The refit's reference normal: a narrower Gaussian (e^{−2s}) than the kernel's, so that
  // near a crease it leans to the face x is on.
  if (refit) sums.reference_normal += t.n * (e * t.e), sums.reference_weight += e * t.e;
  if constexpr (kGradient) sums.g += GradientTerm(m, t, fade);
}

// The plain sums over the neighbours and, with kFaded, the sums faded towards `facing` as well
// (one pass for both: where fading leaves too little, the plain ones are used). Two instances,
// so that the common case (nothing to fade) pays nothing for thin walls.
template <bool kGradient, bool kFaded>
void Accumulate(const IamlsFunction::Impl& m, const Vec3d& x, const Vec3f& facing, bool refit, KernelSums& plain,
                KernelSums& faded) {
  for (const core::Neighbor& q : Neighbours()) {
    const SampleTerm t = Term(m, x, q.index);
    AddTerm<kGradient>(m, t, 1.0, refit, plain);
    if constexpr (kFaded) {
      const double fade = Fade(t.n, facing);
      faded.faded |= fade < 1;
      AddTerm<kGradient>(m, t, fade, refit, faded);
    }
  }
}

// Where ΣΨ is too small to trust F (the kernel's negative lobe takes over at ~1.22 h/ε),
// the value falls back to a Gaussian-weighted mean of the samples' tangent-plane distances
// (an IMLS with a positive kernel: no negative lobe, so its sign is right on both sides of the
// data), scaled like F near the threshold. Only its sign is used there (to classify grid
// corners); the function reports it as undefined so that no surface is placed on it.
template <bool kGradient>
core::FieldGradient Evaluate(const IamlsFunction::Impl& m, const Vec3d& x) {
  std::vector<core::Neighbor>& nn = Neighbours();
  m.tree->Radius(x.cast<float>(), m.radius, nn);
  core::FieldGradient out;
  if (nn.empty()) {
    out.value = std::numeric_limits<double>::quiet_NaN();
    return out;
  }
  const bool refit = m.inv_normal_sigma2 > 0;
  // Only near the builder's thin samples is there anything to fade. The first neighbour the tree
  // reports lies in the leaf nearest x, so its mark stands for x's. Where fading leaves under a
  // tenth of the kernel sum (the tip of a finger, whose samples face every way), the plain sums
  // stay.
  Vec3f facing = Vec3f::Zero();
  if (m.thin_walls && (m.wall_marks[nn.front().index] & IamlsFunction::Impl::kNearThin))
    facing = FacingDirection(m, x, nn);
  KernelSums plain, faded;
  if (facing.isZero()) {
    Accumulate<kGradient, false>(m, x, facing, refit, plain, faded);
  } else {
    Accumulate<kGradient, true>(m, x, facing, refit, plain, faded);
  }
  constexpr double kMinFadedShare = 0.1;
  const bool use_faded = faded.faded && faded.w > kMinFadedShare * plain.w;
  if (use_faded) {
    // F of the samples left, scaled up to the plain kernel sum so that its magnitude does not
    // jump where fading starts.
    const double scale_up = plain.w / faded.w;
    faded.f *= scale_up, faded.g *= scale_up, faded.w = plain.w;
  } else {
    facing = Vec3f::Zero();
  }
  const KernelSums& sums = use_faded ? faded : plain;
  double f = sums.f, w = sums.w;
  Vec3d g = sums.g;
  // Trust F only where the kernel sum is clearly positive: it changes sign ~1.22 h/ε off the
  // data, and F has spurious zeros (ghost sheets) where it does.
  out.defined = w * m.scale > m.min_kernel_sum;
  // The refit only where the nearby normals roughly agree (|mean| ≥ kRefitCoherence): on a thin
  // part (an ear) both sides' normals cancel in the mean, which then points nowhere in
  // particular, and the refit would drop the wrong samples.
  constexpr double kRefitCoherence = 0.85;
  if (refit && out.defined && sums.reference_normal.norm() >= kRefitCoherence * sums.reference_weight &&
      sums.reference_weight > 0) {
    Refit<kGradient>(m, x, sums.reference_normal.normalized(), facing, w, f, g);
  }
  if (out.defined) {
    out.value = f * m.scale;
    out.gradient = g * m.scale;
  } else if (sums.gauss > 0) {
    // Faded like F's where x is near a thin wall (the plain mean of a plate's two faces says
    // "inside" above it), but judged by the fallback's own positive weights: where ΣΨ is this
    // small, the share of ΣΨ left says nothing.
    const bool fade_fallback = faded.faded && faded.gauss > kMinFadedShare * plain.gauss;
    const KernelSums& fallback = fade_fallback ? faded : plain;
    out.value = m.fallback_scale * fallback.gauss_distance / fallback.gauss;
    out.gradient = m.fallback_scale * fallback.gauss_normal / fallback.gauss;
  } else {
    out.value = std::numeric_limits<double>::quiet_NaN();  // Underflow: nothing is known.
  }
  return out;
}

// Row k of the kernel matrix: the neighbours of x_k within the truncation radius (left in `nn`)
// and Ψ_i(x_k) for each (in `psi`); returns s_k = Σ_i ℓ_i(x_k) Ψ_i(x_k).
// Marks sample k kThin when a neighbour faces against it, and then its neighbours kNearThin
// (marks are shared between rows, hence atomic).
double KernelRow(IamlsFunction::Impl& impl, size_t k, std::vector<core::Neighbor>& nn, std::vector<double>& psi) {
  impl.tree->Radius(impl.positions[k], impl.radius, nn);
  const Vec3d xk = impl.positions[k].cast<double>();
  psi.resize(nn.size());
  const Vec3f own_normal = impl.normals[k];
  bool thin = false;
  if (impl.thin_walls) {
    for (const core::Neighbor& q : nn) thin |= FacingAgainst(impl.normals[q.index], own_normal);
  }
  using Impl = IamlsFunction::Impl;
  if (thin) {
    std::atomic_ref<uint8_t>(impl.wall_marks[k]).fetch_or(Impl::kThin, std::memory_order_relaxed);
    for (const core::Neighbor& q : nn) {
      std::atomic_ref<uint8_t>(impl.wall_marks[q.index]).fetch_or(Impl::kNearThin, std::memory_order_relaxed);
    }
  }
  const Vec3f facing = thin ? FacingDirection(impl, xk, nn) : Vec3f::Zero();
  double sk = 0;
  for (size_t j = 0; j < nn.size(); ++j) {
    const Vec3d d = xk - impl.positions[nn[j].index].cast<double>();
    const double si = impl.eps2 * d.squaredNorm() * impl.inv_h2;
    const Vec3d normal = impl.normals[nn[j].index].cast<double>();
    psi[j] = impl.scale * (2.5 - si) * std::exp(-si);
    if (!facing.isZero()) psi[j] *= Fade(normal, facing);
    sk += normal.dot(d) * psi[j];
  }
  return sk;
}

// Kernel matrix rows (symmetric: A_ki = Ψ_i(x_k) at the samples) and the right-hand side s.
absl::StatusOr<KernelMatrix> FillKernelMatrix(IamlsFunction::Impl& impl, std::vector<double>& s,
                                              core::SubContext& setup_ctx, core::JobContext& ctx) {
  return core::BuildKernelMatrix(
      impl.positions.size(),
      [&](size_t k) {
        thread_local std::vector<core::Neighbor> nn;
        impl.tree->Radius(impl.positions[k], impl.radius, nn);
        return static_cast<uint64_t>(nn.size());
      },
      [&](size_t k, uint32_t* column, float* value) {
        thread_local std::vector<core::Neighbor> nn;
        thread_local std::vector<double> psi;
        s[k] = KernelRow(impl, k, nn, psi);
        for (size_t j = 0; j < nn.size(); ++j) {
          column[j] = nn[j].index;
          value[j] = static_cast<float>(psi[j]);
        }
      },
      &ctx, [&](double f) { setup_ctx.Report(0.2 + 0.8 * f); });
}

// The kernel matrix's rows one at a time, never stored: with c empty, s, the row sums ΣΨ at the
// samples and the entry count; with c, A c.
struct StreamedRows {
  std::vector<double> s, row_sum, ac;
  uint64_t entries = 0;
};
absl::Status StreamKernelRows(IamlsFunction::Impl& impl, std::span<const double> c, StreamedRows& out,
                              core::JobContext& ctx) {
  const size_t n = impl.positions.size();
  std::vector<double>& target = c.empty() ? out.s : out.ac;
  target.assign(n, 0.0);
  if (c.empty()) out.row_sum.assign(n, 0.0);
  std::vector<uint32_t> counts(c.empty() ? n : 0);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 1024,
      [&](size_t begin, size_t end) {
        std::vector<core::Neighbor> nn;
        std::vector<double> psi;
        for (size_t k = begin; k < end; ++k) {
          const double sk = KernelRow(impl, k, nn, psi);
          double sum = 0;
          for (size_t j = 0; j < nn.size(); ++j) sum += psi[j] * (c.empty() ? 1.0 : c[nn[j].index]);
          if (c.empty()) {
            out.s[k] = sk;
            out.row_sum[k] = sum;
            counts[k] = static_cast<uint32_t>(nn.size());
          } else {
            out.ac[k] = sum;
          }
        }
      },
      &ctx));
  if (c.empty()) {
    out.entries = 0;
    for (uint32_t count : counts) out.entries += count;
  }
  return absl::OkStatus();
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

namespace {

// Whether nearly all of the cloud is thin walls: over an even sample of about 2048 points, the
// share with a neighbour within `radius` (a kernel width) facing against them is over 95 %. A
// noisy plate is (99.3 % at 0.2 % of the diagonal thick, σ = 0.1 %); a noisy smooth scan with
// thin ears is not, nor a tube wider than the kernel, nor, mostly, a noisy cloud whose normals
// were estimated and flip here and there (the 100k bunny at σ = 0.25 %: 55 %; a ring of 3 % of
// its diameter at σ = 0.1 %: 92 %). Fading made the bunny 15 % slower and 3 % closer with its
// own normals, and the ring with estimated ones 70 % slower in 10 pieces instead of 2.
bool MostlyThinWalls(const OrientedPoints& points, double radius) {
  constexpr size_t kSamples = 2048;
  constexpr double kMostlyWalls = 0.95;
  const size_t n = points.positions.size(), step = std::max<size_t>(1, n / kSamples);
  std::vector<core::Neighbor> nn;
  size_t thin = 0, seen = 0;
  for (size_t i = 0; i < n; i += step, ++seen) {
    points.tree->Radius(points.positions[i], static_cast<float>(radius), nn);
    const Vec3f& own = points.normals[i];
    thin +=
        std::ranges::any_of(nn, [&](const core::Neighbor& q) { return FacingAgainst(points.normals[q.index], own); });
  }
  return static_cast<double>(thin) > kMostlyWalls * static_cast<double>(seen);
}

// ε, the iterations, the cutoff and normal_sigma, given or chosen from the noise (then with the
// noise used).
void ChooseParameters(const IamlsParams& params, const OrientedPoints& points, IamlsStats& stats) {
  IamlsChoice choice;
  if (params.epsilon == 0 || params.iterations < 0 || params.cutoff == 0 || params.normal_sigma < 0 ||
      params.thin_walls < 0) {
    const double neighbor_distance =
        params.spacing == 0 ? points.spacing / params.spacing_scale : core::MeanNearestNeighborDistance(*points.tree);
    const double diagonal = core::Diagonal(core::BoundingBox(points.positions));
    const double sigma = params.noise_level >= 0 ? params.noise_level * diagonal
                                                 : core::EstimateNoise(*points.tree, points.normals).sigma;
    stats.noise_level = diagonal > 0 ? sigma / diagonal : 0;
    stats.noise_ratio = neighbor_distance > 0 ? sigma / neighbor_distance : 0;
    choice = ChooseIamlsParameters(stats.noise_ratio);
  }
  stats.epsilon = params.epsilon > 0 ? params.epsilon : choice.epsilon;
  stats.iterations = params.iterations >= 0 ? params.iterations : choice.iterations;
  stats.cutoff = params.cutoff > 0 ? params.cutoff : choice.cutoff;
  stats.normal_sigma = params.normal_sigma >= 0 ? params.normal_sigma : choice.normal_sigma;
  // Noise as large as a wall flips the side an evaluation finds at random, so a noisy cloud fades
  // thin walls only where it is nearly all walls: blending both faces of a plate loses it.
  if (params.thin_walls < 0 && !choice.thin_walls) {
    choice.thin_walls = MostlyThinWalls(points, points.spacing / stats.epsilon);
  }
  stats.thin_walls = params.thin_walls >= 0 ? params.thin_walls == 1 : choice.thin_walls;
}

double MaxAbsDifference(std::span<const double> a, std::span<const double> b) {
  double most = 0;
  for (size_t k = 0; k < a.size(); ++k) most = std::max(most, std::abs(a[k] - (b.empty() ? 0.0 : b[k])));
  return most;
}

// The kernel's shape for ε: its scale, width and truncation radius.
void SetKernel(IamlsFunction::Impl& impl, double h, double eps, double cutoff) {
  impl.eps2 = eps * eps;
  impl.scale = eps * eps * eps / std::pow(std::numbers::pi, 1.5);
  impl.radius = static_cast<float>(cutoff * h / eps);
}

// Richardson iteration converges iff the spectrum of the symmetric A lies in (0, 2); a margin.
constexpr double kMaxStableEigenvalue = 1.98;
// Lower ε at most this many times looking for one under which it converges: on clouds where the
// kernel matrix's largest eigenvalue does not fall with ε (dense rows seen edge-on, where a
// smaller ε gathers more neighbours), lowering does not help.
constexpr int kMaxLowerings = 6;
constexpr double kMinEpsilon = 0.05;  // The parameter's lower bound.
constexpr double kChosenEpsilonFloor = 0.5;

// Richardson iteration c ← c + (s − A c) on the stored kernel matrix (two or more iterations).
// Where the iteration would diverge under ε, ε is lowered (by the ε³ law of the largest
// eigenvalue, then measured again) when it was chosen; a given ε is refused, with advice that
// was measured to converge. Returns false when no ε tried converges and ε was chosen: the
// caller then makes one iteration, which cannot diverge.
absl::StatusOr<bool> IterateWithMatrix(IamlsFunction::Impl& impl, IamlsStats& stats, bool epsilon_chosen,
                                       std::vector<double>& c, core::SubContext& setup_ctx, core::JobContext& ctx) {
  const size_t n = impl.positions.size();
  const double h = stats.spacing, given = stats.epsilon;
  std::vector<double> s(n);
  double eps = given;
  double previous_eps = 0, previous_lambda = 0;
  for (int attempt = 0;; ++attempt) {
    SetKernel(impl, h, eps, stats.cutoff);
    std::fill(impl.wall_marks.begin(), impl.wall_marks.end(), 0);
    LSQSURF_ASSIGN_OR_RETURN(KernelMatrix a, FillKernelMatrix(impl, s, setup_ctx, ctx));
    auto largest = LargestEigenvalue(a, ctx);
    if (!largest.ok()) return largest.status();
    const double lambda = *largest;
    if (attempt == 0) stats.largest_eigenvalue = lambda;
    if (lambda >= kMaxStableEigenvalue) {
      // λ_max grows like ε^p: p = 3 where the self term 2.5 ε³/π^{3/2} dominates, less where a
      // smaller ε's wider kernel gathers more neighbours; p is measured from the last two tries.
      // Aim at about 1.5.
      double power = 3;
      if (previous_lambda > 0) power = std::log(previous_lambda / lambda) / std::log(previous_eps / eps);
      const double ratio = power > 0.2 ? std::clamp(std::pow(1.5 / lambda, 1 / power), 0.25, 0.95) : 0.0;
      const double next = std::floor(100 * eps * ratio) / 100;
      previous_eps = eps;
      previous_lambda = lambda;
      // A chosen ε is not lowered past half: the kernel's reach, and the cost with it, grows as
      // 1/ε³, and one iteration at the chosen ε is cheaper than three at an eighth of it.
      const bool affordable = !epsilon_chosen || next >= kChosenEpsilonFloor * given;
      if (attempt < kMaxLowerings && next >= kMinEpsilon && next < eps && affordable) {
        eps = next;
        continue;
      }
      if (epsilon_chosen) return false;
      if (attempt == 0 || eps == given) {
        return absl::InvalidArgumentError(
            fmt::format("epsilon={:.3g} makes the iaMLS iteration diverge on this cloud (largest eigenvalue of "
                        "the kernel matrix {:.3g}, must be below 2); use iterations=1",
                        given, stats.largest_eigenvalue));
      }
      return absl::InvalidArgumentError(fmt::format(
          "epsilon={:.3g} makes the iaMLS iteration diverge on this cloud (largest eigenvalue of the kernel "
          "matrix {:.3g}, must be below 2), and so does {:.3g}; use iterations=1",
          given, stats.largest_eigenvalue, eps));
    }
    if (eps != given && !epsilon_chosen) {
      return absl::InvalidArgumentError(
          fmt::format("epsilon={:.3g} makes the iaMLS iteration diverge on this cloud (largest eigenvalue of "
                      "the kernel matrix {:.3g}, must be below 2); epsilon={:.2f} converges here (largest "
                      "eigenvalue {:.3g}), or use iterations=1",
                      given, stats.largest_eigenvalue, eps, lambda));
    }
    stats.epsilon_lowered = attempt;
    stats.epsilon = eps;
    stats.largest_eigenvalue = lambda;
    stats.mean_neighbors = static_cast<double>(a.row_start[n]) / static_cast<double>(n);
    double weight_sum = 0;
    for (float v : a.value) weight_sum += v;
    stats.mean_sample_weight = weight_sum / static_cast<double>(n);
    core::SubContext iter_ctx(ctx, "iterating iaMLS", 0.4, 1.0);
    c.assign(n, 0.0);
    std::vector<double> ac;
    for (int it = 0; it < stats.iterations; ++it) {
      a.Multiply(c, ac);
      double max_residual = 0;
      for (size_t k = 0; k < n; ++k) {
        const double residual = s[k] - ac[k];  // F⁽ⁱᵗ⁾(x_k); the data value there is 0.
        max_residual = std::max(max_residual, std::abs(residual));
        c[k] += residual;
      }
      stats.residuals.push_back(max_residual / h);
      iter_ctx.Report(static_cast<double>(it + 1) / stats.iterations);
      if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
    }
    a.Multiply(c, ac);
    stats.residuals.push_back(MaxAbsDifference(s, ac) / h);
    return true;
  }
}

// No iteration or one: c = 0 or c = s (the first step from c = 0 needs no product), with the
// rows streamed, so the matrix (hundreds of entries per point with the wide kernels of noisy
// clouds) is never stored; one more pass gives the residual after the step.
absl::Status IterateStreamed(IamlsFunction::Impl& impl, IamlsStats& stats, std::vector<double>& c,
                             core::JobContext& ctx) {
  const size_t n = impl.positions.size();
  StreamedRows rows;
  LSQSURF_RETURN_IF_ERROR(StreamKernelRows(impl, {}, rows, ctx));
  stats.mean_neighbors = static_cast<double>(rows.entries) / static_cast<double>(n);
  double weight_sum = 0;
  for (double v : rows.row_sum) weight_sum += v;
  stats.mean_sample_weight = weight_sum / static_cast<double>(n);
  if (stats.iterations == 0) return absl::OkStatus();
  core::SubContext iter_ctx(ctx, "iterating iaMLS", 0.4, 1.0);
  c = rows.s;
  stats.residuals.push_back(MaxAbsDifference(rows.s, {}) / stats.spacing);
  LSQSURF_RETURN_IF_ERROR(StreamKernelRows(impl, c, rows, iter_ctx));
  stats.residuals.push_back(MaxAbsDifference(rows.s, rows.ac) / stats.spacing);
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::unique_ptr<IamlsFunction>> BuildIamls(const core::PointCloud& cloud, const IamlsParams& params,
                                                          core::JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  core::SubContext setup_ctx(ctx, "building iaMLS", 0.0, 0.4);
  auto points = IndexOrientedPoints(cloud, params.spacing, params.spacing_scale, "iaMLS");
  if (!points.ok()) return points.status();
  IamlsStats stats;
  ChooseParameters(params, *points, stats);
  auto impl = std::make_shared<IamlsFunction::Impl>();
  impl->positions = std::move(points->positions);
  impl->normals = std::move(points->normals);
  impl->tree = std::move(points->tree);
  const double h = points->spacing;
  impl->inv_h2 = 1.0 / (h * h);
  SetKernel(*impl, h, stats.epsilon, stats.cutoff);
  impl->inv_facing_radius2 = 4.0 / (h * h);  // ρ = h / 2, about one sample spacing.
  impl->wall_marks.assign(impl->positions.size(), 0);
  impl->thin_walls = stats.thin_walls;
  setup_ctx.Report(0.2);
  stats.spacing = h;
  std::vector<double> c;
  bool iterated = false;
  if (stats.iterations > 1) {
    LSQSURF_ASSIGN_OR_RETURN(iterated, IterateWithMatrix(*impl, stats, params.epsilon == 0, c, setup_ctx, ctx));
  }
  if (!iterated) {
    if (stats.iterations > 1) {  // No chosen ε converged: one step with the first, which cannot diverge.
      stats.iterations = 1;
      stats.iterations_cut = true;
      stats.epsilon_lowered = 0;
      SetKernel(*impl, h, stats.epsilon, stats.cutoff);
      std::fill(impl->wall_marks.begin(), impl->wall_marks.end(), 0);
    }
    LSQSURF_RETURN_IF_ERROR(IterateStreamed(*impl, stats, c, ctx));
  }
  // ΣΨ at the samples sets the scale of "clearly positive" for the ghost-sheet guard.
  impl->fallback_scale = stats.mean_sample_weight;
  impl->min_kernel_sum = params.min_weight * stats.mean_sample_weight;
  impl->inv_normal_sigma2 = stats.normal_sigma > 0 ? 1.0 / (stats.normal_sigma * stats.normal_sigma) : 0.0;
  for (uint8_t marks : impl->wall_marks) stats.thin_samples += (marks & IamlsFunction::Impl::kThin) != 0;
  impl->coefficient.assign(impl->positions.size(), 0.0f);
  for (size_t k = 0; k < c.size(); ++k) impl->coefficient[k] = static_cast<float>(c[k]);
  return std::make_unique<IamlsFunction>(std::move(impl), h, std::move(stats));
}

}  // namespace lsqsurf::mls
