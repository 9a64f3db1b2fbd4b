#include "worker/core/implicit_function.h"

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

}  // namespace lsqsurf::core
