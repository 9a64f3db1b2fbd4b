#include "worker/core/implicit_function.h"

#include <cmath>

#include "worker/core/parallel.h"

namespace lsqsurf::core {

absl::Status ImplicitFunction::ValueOnlyBatch(std::span<const Vec3d> xs, std::span<double> out,
                                              const JobContext* ctx) const {
  return ParallelFor(
      xs.size(), 256,
      [&](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) out[i] = ValueOnly(xs[i]);
      },
      ctx);
}

double RefineRootOnSegment(const ImplicitFunction& field, const Vec3d& a, const Vec3d& b, double fa, double fb,
                           int steps) {
  const bool a_negative = fa < 0;
  // Past `steps`, up to kExtraRootSteps more while |F| is above a millionth of the end values'
  // spread: smooth fields are done by then, but a root next to a kink (a crease, a CSG seam)
  // converges more slowly and would leave the vertex visibly off the surface.
  constexpr int kExtraRootSteps = 8;
  const double tolerance = 1e-6 * std::abs(fa - fb);
  double ta = 0, tb = 1, t = fa / (fa - fb);
  int side = 0;
  for (int step = 0; step < (steps > 0 ? steps + kExtraRootSteps : 0); ++step) {
    const double f = field.ValueOnly(a + t * (b - a));
    if (std::isnan(f) || f == 0.0) return t;
    // Converged: this point is the answer. The update below may rescale a kept end by a factor
    // near 0 when f repeats its value to the last bits (round-off beside the root), and the secant
    // guess after it can then land anywhere in the bracket.
    if (step + 1 >= steps && std::abs(f) <= tolerance) return t;
    // Anderson–Björck: when one end is kept twice, its value is scaled by 1 − f/f_replaced
    // (0.5 where that is not positive), which converges faster than halving it (Illinois).
    if ((f < 0) == a_negative) {
      if (side == -1) fb *= 1 - f / fa > 0 ? 1 - f / fa : 0.5;
      ta = t, fa = f;
      side = -1;
    } else {
      if (side == 1) fa *= 1 - f / fb > 0 ? 1 - f / fb : 0.5;
      tb = t, fb = f;
      side = 1;
    }
    t = ta - fa * (tb - ta) / (fb - fa);
  }
  if (steps <= 0) return t;
  // Still not converged: the secant stalls beside a kink where one end keeps a plateau's value
  // (max(x − h, s) along a box face next to a sphere left a vertex 0.09 of its edge off the
  // surface). Bisection shrinks the bracket 4096-fold at most.
  constexpr int kBisectionSteps = 12;
  for (int step = 0; step < kBisectionSteps; ++step) {
    t = 0.5 * (ta + tb);
    const double f = field.ValueOnly(a + t * (b - a));
    if (std::isnan(f) || f == 0.0 || std::abs(f) <= tolerance) return t;
    ((f < 0) == a_negative ? ta : tb) = t;
  }
  return 0.5 * (ta + tb);
}

}  // namespace lsqsurf::core
