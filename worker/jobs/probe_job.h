// worker/jobs/probe_job.h — the probe job kind: values of a finished volume job's field where
// the user asks for them, from the kept precomputation (no refit).
//
// Points (upload "input": a Draco point cloud, positions only) give values.csv with the header
// x,y,z,value,gx,gy,gz and one row per point in upload order; a point outside the data's domain
// keeps its coordinates and leaves the other columns empty. A grid ("NXxNYxNZ" over the field's
// bounding box) gives field.vti, VTK XML image data that ParaView opens: the field and its
// gradient as point data, NaN outside the domain, and an `inside` mask.
#pragma once

#include <string>

#include "worker/jobs/job_kind.h"

namespace lsqsurf::jobs {

struct ProbeJobParams {
  std::string source;  // Id of a succeeded volume job (required).
  std::string field;   // One of its fields; empty = its first.
  std::string grid;    // "NXxNYxNZ" to resample on a grid; empty = the uploaded points.
};

const JobKind& ProbeJobKind();

}  // namespace lsqsurf::jobs
