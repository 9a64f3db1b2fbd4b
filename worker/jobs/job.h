// worker/jobs/job.h — what the service knows about a job.
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "worker/jobs/engines.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

enum class JobState { kQueued, kRunning, kSucceeded, kFailed, kCancelled };

const char* JobStateName(JobState state);
bool IsTerminal(JobState state);

// Pictures a job draws into its results when it succeeds: preview.png of a surface job's mesh,
// or frame_NNNNN.png of every output frame of a track job (framed on the tracking domain).
struct PreviewSpec {
  bool enabled = false;
  render::RenderParams render;         // Size, camera, colouring; the framing box is the job's.
  double turntable_deg_per_frame = 0;  // Track jobs: azimuth step between frames, −360..360.
};

struct JobSpec {
  std::string method;          // A name from SurfaceMethods().
  ParameterMap parameters;     // Validated against the method.
  int mesh_position_bits = 16; // Draco quantization of the result mesh positions (8..30).
  PreviewSpec preview{};  // Off unless enabled.
};

struct JobRecord {
  std::string id;
  JobSpec spec;
  JobState state = JobState::kQueued;
  std::string stage;           // Current stage while running.
  double progress = 0;         // Overall fraction in [0, 1].
  int attempts = 0;            // Times a worker started the job.
  std::string error;           // Why it failed or was cancelled.
  int64_t created_ms = 0;      // Unix epoch milliseconds.
  int64_t updated_ms = 0;
  int64_t input_points = 0;
  int64_t input_bytes = 0;
  std::vector<std::pair<std::string, double>> statistics;  // Final statistics of a success.
  std::vector<std::string> results;                        // Artifact names of a success.
  uint64_t version = 0;        // Bumped on every change (watchers compare it).
};

}  // namespace lsqsurf::jobs
