// worker/jobs/csg_job.h — the csg job kind: Boolean combinations of analytic primitives and of
// kept PU results (by job id), extracted as one closed mesh (mesh.drc, preview.png on request).
//
// No upload: the expression names everything (csg/expression.h for the syntax). A referenced
// job must have succeeded with method pu and keep_function on; its function is read from its
// results (kPuFunctionArtifact), never refitted. Meshes carry the per-vertex attribute
// "operand": which primitive or job (in order of appearance) the surface comes from there.
#pragma once

#include <memory>
#include <string>

#include "worker/csg/csg.h"
#include "worker/jobs/job_kind.h"
#include "worker/pu/pu.h"

namespace lsqsurf::jobs {

struct CsgJobParams {
  std::string expression;  // Required; csg/expression.h.
  csg::CsgParams extract;  // cell_size (0 = automatic) and the marching options.
};

const JobKind& CsgJobKind();

// A PU function as a csg operand: its points start the extraction, its fitting tree says where
// cells must be fine, and its default extraction cell sets the automatic cell size.
csg::Operand MakePuOperand(std::shared_ptr<const pu::PuFunction> function);

}  // namespace lsqsurf::jobs
