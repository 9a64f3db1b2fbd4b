#include "worker/core/parallel.h"

#include <tbb/blocked_range.h>
#include <tbb/info.h>
#include <tbb/parallel_for.h>
#include <tbb/task_group.h>

#include <atomic>
#include <mutex>

namespace lsqsurf::core {

absl::Status ParallelFor(size_t n, size_t grain, const std::function<void(size_t, size_t)>& body, const JobContext* ctx,
                         const std::function<void(double)>& progress) {
  if (n == 0) return ctx ? ctx->CheckCancelled() : absl::OkStatus();
  grain = grain == 0 ? 1 : grain;
  std::atomic<bool> stop{false};
  std::atomic<size_t> done{0};
  std::mutex progress_mutex;
  // Read without the lock to skip it cheaply, so atomic (relaxed: the lock orders the writes).
  std::atomic<size_t> last_reported{0};
  const size_t report_step = n / 100 + 1;
  // An isolated context keeps a cancellation in this loop from touching unrelated TBB work.
  tbb::task_group_context group;
  tbb::parallel_for(
      tbb::blocked_range<size_t>(0, n, grain),
      [&](const tbb::blocked_range<size_t>& r) {
        if (stop.load(std::memory_order_relaxed)) return;
        if (ctx && ctx->IsCancelled()) {
          stop = true;
          group.cancel_group_execution();
          return;
        }
        body(r.begin(), r.end());
        const size_t now = done.fetch_add(r.size()) + r.size();
        if (progress && now - last_reported.load(std::memory_order_relaxed) >= report_step) {
          std::unique_lock lock(progress_mutex, std::try_to_lock);
          if (lock.owns_lock() && now > last_reported.load(std::memory_order_relaxed)) {
            last_reported.store(now, std::memory_order_relaxed);
            progress(static_cast<double>(now) / static_cast<double>(n));
          }
        }
      },
      group);
  if (stop) return absl::CancelledError("cancelled by request");
  if (progress) progress(1.0);
  return absl::OkStatus();
}

int ParallelismLevel() { return tbb::info::default_concurrency(); }

}  // namespace lsqsurf::core
