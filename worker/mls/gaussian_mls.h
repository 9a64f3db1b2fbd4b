// worker/mls/gaussian_mls.h — the two Gaussian-weighted MLS surfaces the seed compares iaMLS
// with (its Figure 11; METHODS.md §3.4): Adamson–Alexa and Kolluri's IMLS.
//
// Both weight the oriented points p_i (unit normals n_i) within `cutoff` σ of the evaluation
// point x by θ_i(x) = exp(−‖x − p_i‖² / σ²), σ = `width` × h:
//
//  * Adamson–Alexa ("Approximating and intersecting surfaces from points", SGP 2003):
//    F(x) = n(x) · (x − a(x)), with a(x) = Σθ_i p_i / Σθ_i the weighted centroid and n(x) the
//    normalized weighted mean of the normals: the distance to a plane through the local centroid.
//  * Kolluri ("Provably good moving least squares", SODA 2005), an IMLS in the style of
//    Shen, O'Brien and Shewchuk: F(x) = Σθ_i ⟨x − p_i, n_i⟩ / Σθ_i, the weighted mean of the
//    points' tangent-plane distances.
//
// Both shrink a curved surface slightly towards its concave side (the centroid and the mean of
// tangent planes lie inside a sphere by about σ²/2R): the error falls with h at second order.
// ∇F is exact (the derivative of the moving weights included). F is `defined` where at least
// `min_neighbors` points lie within the cutoff and the nearest is within `coverage` × h; farther
// out both are ratios of vanishing sums (0/0) and say nothing. Adamson–Alexa is also undefined
// where the weighted normals cancel (their mean shorter than a quarter), as between the two
// sides of a sheet thinner than σ. Sign as everywhere: F < 0 inside, F > 0 where normals point.
#pragma once

#include <memory>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"

namespace lsqsurf::mls {

enum class GaussianFit { kAdamsonAlexa, kKolluri };

struct GaussianMlsParams {
  GaussianFit fit = GaussianFit::kAdamsonAlexa;
  double spacing = 0.0;        // h in model units; 0 = `spacing_scale` × mean nearest-neighbour distance.
  double spacing_scale = 2.0;  // 0.25..8; as for the other MLS surfaces, so that one h compares them all.
  double width = 1.0;          // σ = width × h, the Gaussian's width, 0.25..4. Larger = smoother.
  double cutoff = 3.0;         // Points beyond cutoff × σ are ignored (weight < 1.3e-4), 2..6.
  int min_neighbors = 6;       // Fewer points within the cutoff: undefined, 3..100.
  double coverage = 1.5;       // Defined within this many h of the nearest point, 0.25..10.
};

// The one description of the fields users set (`fit` is chosen by the method).
const core::ParamTable<GaussianMlsParams>& GaussianMlsParamTable();
absl::Status Validate(const GaussianMlsParams& params);

class GaussianMlsFunction final : public core::ImplicitFunction {
 public:
  ~GaussianMlsFunction() override;
  core::FieldValue Value(const core::Vec3d& x) const override;
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override;
  double ValueOnly(const core::Vec3d& x) const override;

  double spacing() const { return h_; }
  double width() const;  // σ, model units.

  // Defined in the engine's .cc: only its builder can make one, so the public constructor opens
  // nothing to other modules.
  struct Impl;
  explicit GaussianMlsFunction(std::unique_ptr<Impl> impl);

 private:
  std::unique_ptr<Impl> impl_;
  double h_ = 0;
};

// Builds F for an oriented cloud (copied). Errors: kInvalidArgument (no normals, fewer than
// 4 points, non-finite values, coincident points, bad parameters), kCancelled. Cost: a kd-tree;
// an evaluation is one radius query and an O(neighbours) sum (about 28 neighbours by default).
absl::StatusOr<std::unique_ptr<GaussianMlsFunction>> BuildGaussianMls(const core::PointCloud& cloud,
                                                                      const GaussianMlsParams& params,
                                                                      core::JobContext& ctx);

}  // namespace lsqsurf::mls
