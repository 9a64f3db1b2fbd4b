// worker/core/implicit_function.h — the one interface every surface method implements.
//
// A surface is the zero set of F. Sign convention, product-wide: F < 0 inside, F > 0 outside
// (the side the input normals point to). F may be *undefined* where the method has no support
// (too far from the data, or where its weights vanish): extractors never place surface there.
#pragma once

#include <span>

#include "absl/status/status.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

// `defined`: F is trustworthy here and surface may be placed here. Where it is false, `value`
// may still be finite: then only its sign is meaningful (it classifies grid corners as inside
// or outside); it is NaN where nothing at all is known.
struct FieldValue {
  double value = 0.0;
  bool defined = false;
};

struct FieldGradient {
  double value = 0.0;
  Vec3d gradient = Vec3d::Zero();
  bool defined = false;
};

// Implementations must be safe to evaluate concurrently from many threads.
class ImplicitFunction {
 public:
  virtual ~ImplicitFunction() = default;

  virtual FieldValue Value(const Vec3d& x) const = 0;
  virtual FieldGradient ValueAndGradient(const Vec3d& x) const = 0;

  // F's value alone, skipping the `defined` decision where that costs extra (what extractors
  // need for corner signs and root refinement). Default: Value(x).value.
  virtual double ValueOnly(const Vec3d& x) const { return Value(x).value; }
  // F and ∇F likewise without the `defined` decision (then reported true): for moving vertices
  // that already lie on trusted surface. Default: ValueAndGradient(x).
  virtual FieldGradient ValueAndGradientOnly(const Vec3d& x) const { return ValueAndGradient(x); }

  // ValueOnly at many points, in parallel. `out.size()` must equal `xs.size()`. Default: ValueOnly
  // at each; a method with a faster batch path overrides it.
  // Errors: kCancelled when `ctx` is cancelled.
  virtual absl::Status ValueOnlyBatch(std::span<const Vec3d> xs, std::span<double> out,
                                      const JobContext* ctx = nullptr) const;
};

// The root of F on the segment a → b, where F(a) = fa and F(b) = fb have opposite signs, as the
// fraction t ∈ [0, 1] along it: the secant guess refined by `steps` Anderson–Björck (modified
// regula falsi) steps on ValueOnly, superlinear and never leaving the bracket, by up to 8 more
// while |F| stays above 1e-6 |fa − fb| (roots beside a kink converge slowly), and, where that
// still has not converged (the secant stalls beside a plateau), by up to 12 bisections of the
// bracket. Stops early at an exact zero or a NaN value; `steps` = 0 gives the secant guess alone.
double RefineRootOnSegment(const ImplicitFunction& field, const Vec3d& a, const Vec3d& b, double fa, double fb,
                           int steps);

}  // namespace lsqsurf::core
