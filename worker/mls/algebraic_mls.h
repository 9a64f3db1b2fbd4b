// worker/mls/algebraic_mls.h — algebraic-sphere MLS surfaces: RAMLS and APSS.
//
// At every evaluation point x, an algebraic sphere f(y) = u₀ + u_l·y + u₄‖y‖² is fitted to the
// oriented points within the support radius R = support_factor × h, in coordinates centred at x
// and scaled by R (y = (p − x)/R), with weights θ(‖p − x‖/R), θ(s) = (1 − s²)⁴. F(x) is the
// fitted sphere's value at its own origin, Pratt-normalized (u₀ / √(‖u_l‖² − 4u₀u₄), times R) so
// that it approximates the signed distance near the zero set. F < 0 inside, F > 0 on the side
// the normals point to.
//
//  * RAMLS (Gois et al., seed §3; METHODS.md §2.2): (u_l, u₄) minimize Σ w ‖∇f(y_j) − n_j‖² and
//    u₀ then minimizes Σ w f(y_j)², all in closed form; no parameter beyond the support.
//  * APSS (Guennebaud & Gross 2007, normal-constrained fit): u minimizes
//    Σ w f(y_j)² + β Σ w ‖∇f(y_j) − n_j‖², a 5×5 linear least-squares problem. β is
//    dimensionless here (the scaled coordinates make both terms unitless); RAMLS is its β → ∞
//    limit, and small β lets positions outweigh normals.
//
// Both fall back to a plane (u₄ = 0) where the points are too flat to determine a sphere, and
// reproduce a sphere sampled with exact normals exactly. F is `defined` only where at least
// `min_neighbors` points carry weight and the nearest point is within `coverage` × h: a thin
// or absent support extrapolates the sphere into space where no data says anything.
#pragma once

#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"

namespace lsqsurf::mls {

enum class AlgebraicFit { kRamls, kApss };

struct AlgebraicMlsParams {
  AlgebraicFit fit = AlgebraicFit::kRamls;
  double spacing = 0.0;         // h in model units; 0 = `spacing_scale` × mean nearest-neighbour distance.
  double spacing_scale = 2.0;   // 0.25..8. On randomly sampled clouds the mean nearest-neighbour distance
                                // is about half the sampling spacing, so 2 × it is the spacing.
  double support_factor = 3.0;  // R = support_factor × h (the seed's 3h), 1..10.
  int min_neighbors = 6;        // Fewer weighted points: undefined, 4..100.
  double coverage = 1.5;        // Defined within this many h of the nearest point, 0.25..10.
  double apss_beta = 1e6;       // APSS only: weight of the normal term, 0..1e12.
  // Only points whose normal n satisfies n·n* ≥ side_cosine, n* the nearest point's normal, enter
  // a fit; −1 (the default) keeps every point. Where the two sides of a sheet thinner than the
  // support meet, their opposite normals cancel in one fit; a threshold such as −0.5 fits each
  // side alone while keeping the 90° corners of sharp edges whole. −1..1.
  double side_cosine = -1.0;
};

// The one description of the fields users set for `fit` (APSS adds `beta`, the apss_beta
// field); `fit` itself is chosen by the method, not a parameter.
const core::ParamTable<AlgebraicMlsParams>& AlgebraicMlsParamTable(AlgebraicFit fit);
// The table of params.fit.
absl::Status Validate(const AlgebraicMlsParams& params);

// The two fits at one place where the points within the support face two opposite ways (the
// walls of a thin sheet or neck, or two fronts that have come close).
struct SidesAt {
  core::FieldGradient near;  // Fitted to the points facing like the nearest point (the side rule).
  core::FieldGradient far;   // Fitted to the rest; undefined where fewer than min_neighbors carry weight
                             // (no coverage rule: it need not be near x).
  // The far points lie on the side the near points' normals face (a gap between two surfaces),
  // not behind them (the two walls of a neck or sheet). Meaningful only where both fits exist.
  bool far_in_front = false;
};

class AlgebraicMlsFunction final : public core::ImplicitFunction {
 public:
  ~AlgebraicMlsFunction() override;
  core::FieldValue Value(const core::Vec3d& x) const override;
  // The gradient is that of the fitted sphere at x (u_l, normalized like F), not the derivative
  // of the moving fit: exact for a sphere, first-order accurate elsewhere.
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override;
  double ValueOnly(const core::Vec3d& x) const override;
  // F and gradient fitted only to the points whose normal n has n·facing ≥ min_cosine (facing
  // need not be unit), in place of the side rule of the parameters: one side of a sheet thinner
  // than the support, chosen by the caller. `defined` counts only those points.
  core::FieldGradient ValueAndGradientFacing(const core::Vec3d& x, const core::Vec3d& facing, double min_cosine) const;
  // Both sides at x in one neighbour query: the points whose normal n has n·n* ≥ side_cosine (n*
  // the nearest point's; 0 when the parameters keep every point) and the others.
  SidesAt Sides(const core::Vec3d& x) const;

  double spacing() const { return h_; }
  double support_radius() const;

  // Defined in the engine's .cc: only its builder can make one, so the public constructor opens
  // nothing to other modules.
  struct Impl;
  explicit AlgebraicMlsFunction(std::unique_ptr<Impl> impl);

 private:
  std::unique_ptr<Impl> impl_;
  double h_ = 0;
};

// Builds F for an oriented cloud (copied). Errors: kInvalidArgument (no normals, fewer than
// 4 points, non-finite values, bad parameters), kCancelled. Cost: a kd-tree; each evaluation is
// one radius query and an O(neighbours) sum.
absl::StatusOr<std::unique_ptr<AlgebraicMlsFunction>> BuildAlgebraicMls(const core::PointCloud& cloud,
                                                                        const AlgebraicMlsParams& params,
                                                                        core::JobContext& ctx);

}  // namespace lsqsurf::mls
