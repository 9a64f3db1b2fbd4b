// worker/core/parallel.h — the shared parallel loop every engine uses.
//
// Backed by oneTBB's work-stealing scheduler: one process-wide pool, safe to call from several
// jobs at once (their chunks interleave on the same cores), and nested calls do not deadlock.
#pragma once

#include <cstddef>
#include <functional>

#include "absl/status/status.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

// Calls `body(begin, end)` on disjoint chunks covering [0, n), in parallel. Cancellation is
// polled once per chunk; after it is seen, the remaining chunks are skipped and kCancelled is
// returned. `progress`, when given, receives the completed fraction in [0, 1] (rate-limited).
// `grain` is the smallest chunk worth a task (choose it so a chunk takes ~0.1–1 ms).
absl::Status ParallelFor(size_t n, size_t grain, const std::function<void(size_t, size_t)>& body,
                         const JobContext* ctx = nullptr, const std::function<void(double)>& progress = nullptr);

// Number of worker threads the pool runs (the machine's cores unless limited).
int ParallelismLevel();

}  // namespace lsqsurf::core
