// worker/jobs/track_job.h — the front-tracking job kind (method "track").
//
// A job advects an interface (an uploaded oriented cloud, or one of the benchmark shapes) through
// a velocity field and writes one artifact per output frame plus a statistics table:
//   frame_NNNNN.drc       Draco point cloud with normals, NNNNN the step;
//   frame_NNNNN_mesh.drc  with meshes: the frame's RAMLS surface as a Draco mesh;
//   stats.csv             step,time,points,volume,volume_change (change relative to step 0), and
//                         mesh_volume (the mesh's enclosed volume) with meshes;
//   frame_NNNNN.png       with a preview: the frame's mesh (with meshes) or points, framed on the
//                         tracking domain (the unit cube, or the velocity grid's extent);
//   summary.txt           for a named shape run to where the field brings it back (one revolution
//                         of the rotation, or t = T of the deformation): e1_rel= and
//                         volume_change=, both fractions.
#pragma once

#include "worker/front/front_tracking.h"
#include "worker/jobs/job_kind.h"

namespace lsqsurf::jobs {

// The values are stored with accepted jobs: never renumber.
enum class TrackInterface { kUploaded = 0, kSphere = 1, kZalesak = 2 };
enum class TrackField { kRotation = 0, kDeformation = 1, kUploaded = 2 };

struct TrackJobParams {
  TrackJobParams() {
    tracking.steps = 100;
    tracking.output_stride = 10;
  }
  TrackInterface interface = TrackInterface::kSphere;
  TrackField field = TrackField::kRotation;
  double period = 3;                                                  // T of the deformation field, time units.
  front::TimeModulation modulation = front::TimeModulation::kCosine;  // How it changes in time.
  int cells = 128;                 // Background grid cells per unit length (h = 1/cells).
  bool meshes = false;             // Also write frame meshes and a mesh_volume column.
  front::TrackingParams tracking;  // h is set from `cells`.
};

const JobKind& TrackJobKind();

}  // namespace lsqsurf::jobs
