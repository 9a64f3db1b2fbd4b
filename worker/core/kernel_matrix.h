// worker/core/kernel_matrix.h — the sparse kernel matrix of the iterated approximate MLS methods
// (iaMLS surfaces in worker/mls, volume fields in worker/volume): A_ki = Ψ_i(x_k) in CSR form,
// built in two passes and multiplied in parallel. The iterations themselves (Richardson steps,
// the power steps that bound them) differ between the two and stay with each engine.
#pragma once

#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

// Float values: the iterations need ~1e-6 relative accuracy at most, and this halves the largest
// buffer (about 140 million entries for a million iaMLS samples).
struct KernelMatrix {
  std::vector<uint64_t> row_start;  // rows() + 1 offsets into column and value.
  std::vector<uint32_t> column;
  std::vector<float> value;

  size_t rows() const { return row_start.empty() ? 0 : row_start.size() - 1; }
  uint64_t entries() const { return row_start.empty() ? 0 : row_start.back(); }
  // out = A · in for `columns` interleaved columns (in: kernels × columns, out: rows × columns).
  void Multiply(std::span<const double> in, std::vector<double>& out, int columns = 1) const;
};

// A kernel matrix of `rows` rows, filled in place: `count(k)` is the number of entries of row k,
// then `fill(k, columns, values)` writes exactly that many (a per-row staging copy would double
// the peak). Both are called from worker threads, each row once per pass. `progress` sees the two
// passes as 0..0.5 and 0.5..1. Errors: kCancelled.
absl::StatusOr<KernelMatrix> BuildKernelMatrix(size_t rows, const std::function<uint64_t(size_t)>& count,
                                               const std::function<void(size_t, uint32_t*, float*)>& fill,
                                               const JobContext* ctx,
                                               const std::function<void(double)>& progress = nullptr);

}  // namespace lsqsurf::core
