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
// Truncation: Ψ is cut at ε r = `cutoff` (default 4, radius 4h/ε); there |Ψ| < 2.7e-7 ε³ and the
// neglected tail of a sum over a uniformly sampled surface is about 1e-6 of the kernel's mass.
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
  // Defaults: the seed's ε = 0.8 with h = mean nearest-neighbour distance leaves holes on
  // randomly sampled clouds (there the mean NN distance is about half the sampling spacing, so
  // the kernel is narrower than the gaps), and ε = 0.8 with twice that h makes the iteration
  // diverge (largest eigenvalue 2.3). h = 2 × NN distance with ε = 0.6 is the measured optimum.
  double epsilon = 0.6;        // Shape parameter ε (dimensionless), 0.05..3. Larger = more detail.
  int iterations = 3;          // Residual-correction steps, 0..20. More = closer fit, less smoothing.
  double spacing = 0.0;        // h in model units; 0 = `spacing_scale` × mean nearest-neighbour distance.
  double spacing_scale = 2.0;  // Multiplier of the measured spacing when `spacing` is 0; 0.25..8.
  double cutoff = 4.0;         // Kernel truncation at ε r = cutoff, 2..8.
  double min_weight = 0.1;     // F is undefined where ΣΨ < min_weight × (mean ΣΨ at the samples), 0..1:
                               // the guard against the ghost sheets of the kernel's negative lobe.
};

// The one description of every IamlsParams field (range, unit, meaning).
const core::ParamTable<IamlsParams>& IamlsParamTable();
// The table's checks, with messages a user can act on (the data-dependent divergence check
// happens in BuildIamls).
absl::Status Validate(const IamlsParams& params);

struct IamlsStats {
  double spacing = 0;             // h actually used (model units).
  double largest_eigenvalue = 0;  // Of the kernel matrix; the iteration needs it below 2.
  std::vector<double> residuals;  // max_i |F(x_i)| / h before each iteration and after the last.
  double mean_neighbors = 0;      // Points within the truncation radius, per point.
  double mean_sample_weight = 0;  // Mean ΣΨ at the samples.
};

class IamlsFunction final : public core::ImplicitFunction {
 public:
  core::FieldValue Value(const core::Vec3d& x) const override;
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override;

  const IamlsStats& stats() const { return stats_; }
  double spacing() const { return h_; }

 private:
  friend absl::StatusOr<std::unique_ptr<IamlsFunction>> BuildIamls(const core::PointCloud&, const IamlsParams&,
                                                                   core::JobContext&);
  IamlsFunction() = default;

 public:
  struct Impl;  // Defined in iamls.cc.

 private:
  std::shared_ptr<const Impl> impl_;
  double h_ = 0;
  IamlsStats stats_;
};

// Builds F for an oriented cloud (the cloud is copied; it need not outlive the function).
// Errors: kInvalidArgument (no normals, fewer than 4 points, bad parameters, or an ε for which
// the iteration diverges on this cloud — the message says which ε to use), kCancelled.
// Cost: one radius query per point plus `iterations` sparse products (~50/ε² neighbours each).
absl::StatusOr<std::unique_ptr<IamlsFunction>> BuildIamls(const core::PointCloud& cloud, const IamlsParams& params,
                                                          core::JobContext& ctx);

}  // namespace lsqsurf::mls
