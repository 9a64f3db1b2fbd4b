#include "worker/core/kernel_matrix.h"

#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::core {

void KernelMatrix::Multiply(std::span<const double> in, std::vector<double>& out, int columns) const {
  const size_t n = rows();
  out.assign(n * static_cast<size_t>(columns), 0.0);
  (void)ParallelFor(n, 2048, [&](size_t begin, size_t end) {
    for (size_t k = begin; k < end; ++k) {
      double* o = &out[k * static_cast<size_t>(columns)];
      for (uint64_t e = row_start[k]; e < row_start[k + 1]; ++e) {
        const double v = value[e];
        const double* x = &in[static_cast<size_t>(column[e]) * static_cast<size_t>(columns)];
        for (int c = 0; c < columns; ++c) o[c] += v * x[c];
      }
    }
  });
}

absl::StatusOr<KernelMatrix> BuildKernelMatrix(size_t rows, const std::function<uint64_t(size_t)>& count,
                                               const std::function<void(size_t, uint32_t*, float*)>& fill,
                                               const JobContext* ctx, const std::function<void(double)>& progress) {
  KernelMatrix a;
  a.row_start.assign(rows + 1, 0);
  auto report = [&](double from) {
    return progress ? std::function<void(double)>([&progress, from](double f) { progress(from + 0.5 * f); })
                    : std::function<void(double)>();
  };
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      rows, 1024,
      [&](size_t begin, size_t end) {
        for (size_t k = begin; k < end; ++k) a.row_start[k + 1] = count(k);
      },
      ctx, report(0.0)));
  for (size_t k = 0; k < rows; ++k) a.row_start[k + 1] += a.row_start[k];
  a.column.resize(a.row_start[rows]);
  a.value.resize(a.row_start[rows]);
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      rows, 1024,
      [&](size_t begin, size_t end) {
        for (size_t k = begin; k < end; ++k) fill(k, a.column.data() + a.row_start[k], a.value.data() + a.row_start[k]);
      },
      ctx, report(0.5)));
  return a;
}

}  // namespace lsqsurf::core
