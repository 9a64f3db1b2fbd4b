// worker/jobs/front_job.h — the front-tracking job kind (method name "track").
//
// A job advects an interface (an uploaded oriented cloud, or one of the benchmark shapes) through
// a named velocity field and writes one artifact per output frame plus a statistics table:
//   frame_NNNNN.drc  Draco point cloud with normals, NNNNN the step;
//   frame_NNNNN_mesh.drc  with meshes=1: the frame's RAMLS surface as a Draco mesh;
//   stats.csv        step,time,points,volume,volume_change (change relative to step 0), and
//                    mesh_volume (the mesh's enclosed volume) with meshes=1;
//   frame_NNNNN.png  with pictures: the frame's mesh (with meshes=1) or points, framed on the
//                    tracking domain (the unit cube, or the velocity grid's extent);
//   summary.txt      for a named shape run to where the field brings it back (one revolution of
//                    the rotation, or t = T of the deformation): e1_rel= and volume_change=,
//                    both fractions.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/io/vtk_grid.h"
#include "worker/jobs/engines.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

inline constexpr char kTrackMethod[] = "track";

MethodSpec TrackMethod();

// Whether the request tracks an uploaded interface (otherwise it names a shape and needs none).
bool TrackNeedsUpload(const ParameterMap& parameters);
// Whether the request moves the interface with an uploaded velocity grid (field = 2).
bool TrackNeedsVelocity(const ParameterMap& parameters);

struct TrackOutput {
  std::vector<std::pair<std::string, double>> statistics;
  std::vector<std::string> artifacts;  // In the order written.
};

// Pictures of the output frames.
struct FramePictures {
  render::Renderer* renderer = nullptr;  // nullptr: none could be made; every picture fails.
  render::RenderParams params;         // Its framing box is replaced by the tracking domain.
  double turntable_deg_per_frame = 0;  // Added to the azimuth from one output frame to the next.
};

// Runs a validated "track" request; `interface` is the uploaded cloud (needed with normals when
// TrackNeedsUpload), `velocity` the uploaded grid (needed when TrackNeedsVelocity), and the
// artifacts are written into `out_dir`, with a picture of each frame when `pictures` is given
// (a picture that fails is counted in the statistic preview_failures, not an error). Errors:
// kInvalidArgument, kResourceExhausted, kFailedPrecondition, kCancelled, kUnavailable (writing
// failed).
absl::StatusOr<TrackOutput> RunTrackJob(const ParameterMap& parameters, const core::PointCloud* interface,
                                        const io::VectorGrid* velocity, const std::string& out_dir,
                                        core::JobContext& ctx, const FramePictures* pictures = nullptr);

}  // namespace lsqsurf::jobs
