// tests/latch_kind.h — a job kind that holds its jobs until a test lets them go.
//
// Installed through JobServiceOptions::kind_overrides, it replaces a method's engine so that a
// test can act on a job that is certainly running (cancel, delete, shutdown) without racing it.
#pragma once

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "worker/jobs/job_kind.h"

namespace lsqsurf::testing {

// A kind that holds every job it runs until released (or cancelled), so that tests can act on a
// job that is certainly running.
class LatchKind final : public jobs::JobKind {
 public:
  std::string_view name() const override { return "latch"; }
  std::vector<jobs::MethodInfo> Methods() const override { return {}; }
  absl::StatusOr<jobs::CheckedInput> CheckUploads(const jobs::JobSpec&, const jobs::Uploads&,
                                                  const jobs::InputLimits&) const override {
    std::unique_lock lock(mutex_);
    ++checking_;
    changed_.notify_all();
    changed_.wait(lock, [this] { return !checks_held_; });
    return jobs::CheckedInput{1, nullptr, {}};
  }
  absl::StatusOr<jobs::Statistics> Run(const jobs::JobSpec&, const jobs::Uploads&,
                                       jobs::RunEnvironment& env) const override {
    for (const auto& [name, bytes] : early_) {
      if (absl::Status s = env.sink.Write(name, bytes); !s.ok()) return s;
    }
    for (const auto& [stage, fraction] : progress_) env.context.ReportProgress(stage, fraction);
    std::unique_lock lock(mutex_);
    ++started_;
    changed_.notify_all();
    // The job context has no wake-up of its own; a short wait keeps the cancel check prompt.
    while (!released_) {
      if (env.context.IsCancelled()) return absl::CancelledError("cancelled");
      changed_.wait_for(lock, std::chrono::milliseconds(5));
    }
    if (absl::Status s = env.sink.Write("held.txt", "released"); !s.ok()) return s;
    return jobs::Statistics{{"held", 1}};
  }
  // Artifacts every job writes before it holds (set before jobs run).
  void WriteBeforeHolding(std::string name, std::string bytes) {
    early_.emplace_back(std::move(name), std::move(bytes));
  }
  // Progress every job reports, in order, before it holds (set before jobs run).
  void ReportBeforeHolding(std::vector<std::pair<std::string, double>> progress) { progress_ = std::move(progress); }
  // Blocks until `n` jobs have started.
  void WaitStarted(int n) const {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return started_ >= n; });
  }
  int started() const {
    std::lock_guard lock(mutex_);
    return started_;
  }
  // Holds submissions in their upload check (on the server's submission threads) until
  // ReleaseChecks; WaitChecking(n) blocks until `n` checks have begun.
  void HoldChecks() {
    std::lock_guard lock(mutex_);
    checks_held_ = true;
  }
  void WaitChecking(int n) const {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return checking_ >= n; });
  }
  bool ChecksHeld() const {
    std::lock_guard lock(mutex_);
    return checks_held_;
  }
  void ReleaseChecks() const {
    std::lock_guard lock(mutex_);
    checks_held_ = false;
    changed_.notify_all();
  }
  void Release() const {
    std::lock_guard lock(mutex_);
    released_ = true;
    changed_.notify_all();
  }

 private:
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  mutable int started_ = 0;
  mutable bool released_ = false;
  mutable int checking_ = 0;
  mutable bool checks_held_ = false;
  std::vector<std::pair<std::string, std::string>> early_;
  std::vector<std::pair<std::string, double>> progress_;
};

}  // namespace lsqsurf::testing
