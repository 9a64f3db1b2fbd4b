// worker/mls/iamls.h — iterated approximate MLS surfaces (iaMLS).
//
// Fasshauer & Zhang, "Iterated approximate moving least squares approximation" (2007), applied
// to oriented points as in the seed paper §4 (Gois et al.). Every point x_i with unit normal n_i
// carries the linear function ℓ_i(x) = ⟨x − x_i, n_i⟩ (positive outside) and the Laguerre–Gaussian
// generating function of order 1 in 3-D,
//     Ψ_i(x) = (ε³ / π^{3/2}) (5/2 − ε² r²) exp(−ε² r²),   r = ‖x − x_i‖ / h.
// F⁽⁰⁾ = Σ ℓ_i Ψ_i; each iteration adds Σ [0 − F⁽ⁿ⁾(x_i)] Ψ_i, driving F to zero at the samples.
// The iterations fold into one coefficient per point, F(x) = Σ (ℓ_i(x) − c_i) Ψ_i(x), so an
// evaluation costs a single neighbour sum however many iterations were run.
//
// Truncation: Ψ is cut at ε r = `cutoff` (4 on clean clouds, radius 4h/ε); there |Ψ| < 2.7e-7 ε³
// and the neglected tail of a sum over a uniformly sampled surface is about 1e-6 of the kernel's
// mass (at cutoff 3, used on noisy clouds, about 1e-3: far below the noise).
// Ghost sheets: ΣΨ changes sign at about 1.22 h/ε from the data (the kernel's negative lobe),
// where F has spurious zeros; F is reported undefined wherever ΣΨ is not clearly positive
// (see `min_weight`), so no extractor places surface there.
#pragma once

#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"

namespace lsqsurf::mls {

struct IamlsParams {
  // ε, the iterations, the cutoff and normal_sigma are chosen from the scan's noise unless given
  // (see ChooseIamlsParameters): clean clouds get ε = 0.6, 3 iterations, cutoff 4 and no refit;
  // noisy ones a wider kernel and one iteration, since every iteration fits the noise a little
  // more, and the crease-keeping refit, since the wider kernel rounds creases more.
  double epsilon = 0;          // Shape parameter ε (dimensionless), 0.05..3; 0 = chosen. Larger = more detail.
  int iterations = -1;         // Residual-correction steps, 0..20; -1 = chosen. More = closer fit, less smoothing.
  double spacing = 0.0;        // h in model units; 0 = `spacing_scale` × mean nearest-neighbour distance.
  double spacing_scale = 2.0;  // Multiplier of the measured spacing when `spacing` is 0; 0.25..8.
  double cutoff = 0;           // Kernel truncation at ε r = cutoff, 2..8; 0 = chosen.
  double min_weight = 0.1;     // F is undefined where ΣΨ < min_weight × (mean ΣΨ at the samples), 0..1:
                               // the guard against the ghost sheets of the kernel's negative lobe.
  double noise_level = -1;     // Noise σ along the normal as a share of the bounding-box diagonal, for
                               // the choice: -1 estimates it (core::EstimateNoise), 0 declares the data
                               // exact, up to 0.1.
  // Crease-keeping refit, -1 (chosen: 0.5 on noisy clouds, off on clean ones), 0 (off) or
  // 0.2..2: F is evaluated a second time with each sample's weight scaled by
  // exp(−|n_i − n̄|² / normal_sigma²), n̄ the samples' mean normal near x (a Gaussian half as
  // wide as the kernel), so the other face of a crease drops out of the blend (robust-MLS normal
  // weights). Skipped where the nearby normals disagree too much to have a mean (thin parts).
  // Where it acts it is a second pass over the neighbours.
  double normal_sigma = -1;
  // Thin walls (plates, fingers, sharp wedges thinner than the kernel): each evaluation fades out
  // the samples that face against the ones nearest it, so the far side of the wall does not
  // cancel the near side. -1: chosen (on for clean clouds; off for noisy ones, where noise as
  // large as the wall makes the nearest samples' side flip at random), 0 off, 1 on.
  int thin_walls = -1;
};

// What the automatic choice picks from ρ = σ / (mean nearest-neighbour distance), σ the noise
// along the normal. Measured on the bunny, spot and fandisk at 100k points (README): on clean
// clouds ρ is about 0.01 to 0.09 (the estimator's residual of curvature), and ε = 0.6 with 3
// iterations fits best; from ρ = 0.15 on, one iteration with ε = 0.55 / (1 + ρ/1.5) (at least
// 0.3), cutoff 3 and the crease-keeping refit at normal_sigma 0.5 balances the noise left
// against the detail (and the creases) smoothed away.
struct IamlsChoice {
  double epsilon = 0.6;
  int iterations = 3;
  double cutoff = 4;
  double normal_sigma = 0;
  bool thin_walls = true;
};
IamlsChoice ChooseIamlsParameters(double noise_ratio);

// The one description of every IamlsParams field (range, unit, meaning).
const core::ParamTable<IamlsParams>& IamlsParamTable();
// The table's checks, with messages a user can act on (the data-dependent divergence check
// happens in BuildIamls).
absl::Status Validate(const IamlsParams& params);

struct IamlsStats {
  double spacing = 0;  // h actually used (model units).
  double epsilon = 0;  // ε, iterations and cutoff used (given or chosen).
  int iterations = 0;
  double cutoff = 0;
  double normal_sigma = 0;        // The crease-keeping refit's σ_n used (0: off).
  bool thin_walls = false;        // Whether thin walls were faded (given or chosen).
  double noise_level = -1;        // Noise σ used for the choice, share of the bounding-box diagonal (as
                                  // PuStats::noise_estimate); -1 when nothing was chosen.
  double noise_ratio = -1;        // σ / mean nearest-neighbour distance; -1 likewise.
  double largest_eigenvalue = 0;  // Of the kernel matrix; the iteration needs it below 2 (0: not computed,
                                  // one iteration cannot diverge).
  // A chosen ε under which the iteration would diverge is lowered until it does not (times it
  // was), and where lowering does not help the iterations are cut to one (which cannot diverge).
  int epsilon_lowered = 0;
  bool iterations_cut = false;
  std::vector<double> residuals;  // max_i |F(x_i)| / h before each iteration and after the last.
  double mean_neighbors = 0;      // Points within the truncation radius, per point.
  double mean_sample_weight = 0;  // Mean ΣΨ at the samples.
  int64_t thin_samples = 0;       // Samples with a neighbour facing against them (thin walls, see the .cc).
};

class IamlsFunction final : public core::ImplicitFunction {
 public:
  core::FieldValue Value(const core::Vec3d& x) const override;
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override;

  const IamlsStats& stats() const { return stats_; }
  double spacing() const { return h_; }

  // Defined in the engine's .cc: only its builder can make one, so the public constructor opens
  // nothing to other modules.
  struct Impl;
  IamlsFunction(std::shared_ptr<const Impl> impl, double spacing, IamlsStats stats)
      : impl_(std::move(impl)), h_(spacing), stats_(std::move(stats)) {}

 private:
  std::shared_ptr<const Impl> impl_;
  double h_ = 0;
  IamlsStats stats_;
};

// Builds F for an oriented cloud (the cloud is copied; it need not outlive the function).
// Errors: kInvalidArgument (no normals, fewer than 4 points, bad parameters, or an ε for which
// the iteration diverges on this cloud — the message says which ε to use), kCancelled.
// Cost: one radius query per point plus `iterations` sparse products (~50/ε² neighbours each);
// with at most one iteration the kernel matrix is never stored (two radius queries per point).
absl::StatusOr<std::unique_ptr<IamlsFunction>> BuildIamls(const core::PointCloud& cloud, const IamlsParams& params,
                                                          core::JobContext& ctx);

}  // namespace lsqsurf::mls
