// worker/core/job_context.h — progress and cancellation for long operations.
//
// Engines never print and never know about the service. They report progress as a stage name
// plus an overall fraction in [0, 1], and poll cancellation at iteration boundaries (per chunk
// of a parallel loop, per iteration of a solver), never in inner loops.
#pragma once

#include <atomic>
#include <chrono>
#include <string>
#include <string_view>

#include "absl/status/status.h"

namespace lsqsurf::core {

// Wall-clock seconds since `start`, for the timings in job statistics.
inline double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// Implementations must be thread-safe: parallel loops report from several threads.
class JobContext {
 public:
  virtual ~JobContext() = default;
  // `fraction` is the overall progress of the operation in [0, 1].
  virtual void ReportProgress(std::string_view stage, double fraction) = 0;
  virtual bool IsCancelled() const = 0;

  // kCancelled when cancellation was requested, OK otherwise.
  absl::Status CheckCancelled() const;
};

// A context that ignores progress and can be cancelled from another thread. Used where nobody
// watches: tests, benchmarks, the client's `compare`.
class LocalJobContext : public JobContext {
 public:
  void ReportProgress(std::string_view, double) override {}
  bool IsCancelled() const override { return cancelled_.load(std::memory_order_relaxed); }
  void Cancel() { cancelled_.store(true, std::memory_order_relaxed); }

 private:
  std::atomic<bool> cancelled_{false};
};

// Maps the [0, 1] progress of a sub-step onto [begin, end] of the parent's progress, under a
// stage name of its own. Cancellation is forwarded unchanged.
class SubContext : public JobContext {
 public:
  SubContext(JobContext& parent, std::string stage, double begin, double end)
      : parent_(parent), stage_(std::move(stage)), begin_(begin), end_(end) {}
  void ReportProgress(std::string_view stage, double fraction) override;
  bool IsCancelled() const override { return parent_.IsCancelled(); }
  // Reports `fraction` of this sub-step under its own stage name.
  void Report(double fraction) { ReportProgress(stage_, fraction); }

 private:
  JobContext& parent_;
  std::string stage_;
  double begin_;
  double end_;
};

}  // namespace lsqsurf::core
