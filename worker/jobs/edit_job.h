// worker/jobs/edit_job.h — the edit job kind: a local edit of a kept PU function (pu::EditPu)
// and the edited surface, as a new result beside the source's (which stays).
//
// No upload: `source` names a succeeded pu (or edit) job kept with its function. The result is
// mesh.drc (as a pu job's, with the depth/degree/feature attributes), function.lqpu (so that
// edits chain) and preview.png on request. Statistics: fits_replaced, fits_after,
// points_removed, edit_reach (F is unchanged farther than this from the centre), load_seconds,
// edit_seconds, extract_seconds.
#pragma once

#include <string>

#include "worker/jobs/job_kind.h"
#include "worker/pu/pu.h"

namespace lsqsurf::jobs {

struct EditJobParams {
  std::string source;  // Id of a succeeded pu or edit job with a kept function (required).
  pu::PuEdit edit;
  pu::PuExtractParams extract;
};

const JobKind& EditJobKind();

}  // namespace lsqsurf::jobs
