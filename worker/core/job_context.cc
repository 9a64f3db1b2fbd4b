#include "worker/core/job_context.h"

#include <algorithm>

namespace lsqsurf::core {

absl::Status JobContext::CheckCancelled() const {
  if (IsCancelled()) return absl::CancelledError("cancelled by request");
  return absl::OkStatus();
}

void SubContext::ReportProgress(std::string_view stage, double fraction) {
  // A nested sub-step keeps its own, more specific stage name.
  parent_.ReportProgress(stage.empty() ? std::string_view(stage_) : stage,
                         begin_ + (end_ - begin_) * std::clamp(fraction, 0.0, 1.0));
}

}  // namespace lsqsurf::core
