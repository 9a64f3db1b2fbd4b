// worker/jobs/job_pictures.h — the pictures a service draws of its jobs' results (Render), with
// its slots per server and per user, and the renderer the runs draw their previews with.
//
#pragma once

#include <memory>
#include <mutex>
#include <string>

#include "absl/status/statusor.h"
#include "worker/core/fair_slots.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"
#include "worker/jobs/job_service_options.h"
#include "worker/jobs/job_table.h"

namespace lsqsurf::render {
class SharedRenderer;
struct RenderParams;
}  // namespace lsqsurf::render

namespace lsqsurf::jobs {

class VolumePictures;  // volume_job.h

// Thread-safe.
class JobPictures {
 public:
  // At most `max_renders` pictures at once (a named user half of them, rounded up); a volume
  // picture's grid within `max_render_bytes`.
  JobPictures(const JobTable& table, BlobStore& blobs, int max_renders, int64_t max_render_bytes);
  ~JobPictures();

  // JobService::Render for a record its caller `owner` may see.
  absl::StatusOr<RenderedPicture> Render(const std::string& owner, const JobRecord& record, const std::string& name,
                                         const core::ParamSet& view, const core::JobContext* ctx);
  // Whether pictures can be drawn (makes the renderer on first use, about 0.1 s); why not.
  absl::Status RendererStatus();
  bool CanRender() { return RendererStatus().ok(); }
  render::SharedRenderer& renderer() { return *renderer_; }

 private:
  // A picture of every mesh part the record lists (the Render path for mesh-part-NNNNN.lqm).
  absl::StatusOr<RenderedPicture> RenderMeshParts(const JobRecord& record, const render::RenderParams& params);
  // A picture of a volume job's stored field (the Render path for field.lqvf).
  absl::StatusOr<RenderedPicture> RenderVolumeField(const std::string& id, const std::string& bytes,
                                                    const render::RenderParams& params, const core::JobContext* ctx);
  // Takes one of the max_renders slots for `owner`; false when none is left to them.
  bool TakeSlot(const std::string& owner);
  void ReleaseSlot(const std::string& owner);

  const JobTable& table_;
  BlobStore& blobs_;
  const int max_renders_;
  std::unique_ptr<render::SharedRenderer> renderer_;
  std::mutex slots_mutex_;  // Guards slots_.
  core::FairSlots slots_;   // Pictures being drawn, max_renders of them.
  std::unique_ptr<VolumePictures> volume_pictures_;
};

}  // namespace lsqsurf::jobs
