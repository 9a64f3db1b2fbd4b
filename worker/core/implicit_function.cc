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
  double ta = 0, tb = 1, t = fa / (fa - fb);
  int side = 0;
  for (int step = 0; step < steps; ++step) {
    const double f = field.ValueOnly(a + t * (b - a));
    if (std::isnan(f) || f == 0.0) break;
    if ((f < 0) == a_negative) {
      ta = t, fa = f;
      if (side == -1) fb *= 0.5;
      side = -1;
    } else {
      tb = t, fb = f;
      if (side == 1) fa *= 0.5;
      side = 1;
    }
    t = ta - fa * (tb - ta) / (fb - fa);
  }
  return t;
}

}  // namespace lsqsurf::core
