// worker/jobs/job_events.h — what the job service reports as it works, for metrics.
//
// A narrow hook: the service calls it from its worker threads, without its lock held, so an
// implementation must be thread-safe and quick. Every method does nothing by default.
#pragma once

#include <string>

#include "worker/jobs/job.h"

namespace lsqsurf::jobs {

class JobEvents {
 public:
  virtual ~JobEvents() = default;
  // A job this service runs left `stage` after `seconds` (the stage names of JobRecord::stage).
  virtual void StageEnded(const std::string& method, const std::string& stage, double seconds) {
    (void)method, (void)stage, (void)seconds;
  }
  // A job this service ran ended in `state` after `seconds`.
  virtual void JobEnded(const std::string& method, JobState state, double seconds) {
    (void)method, (void)state, (void)seconds;
  }
};

}  // namespace lsqsurf::jobs
