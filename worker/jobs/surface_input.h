// worker/jobs/surface_input.h — a surface job's uploads decoded and checked: one cloud, or a
// cloud in Draco parts (InputPartSlot) that a streaming method reads one part at a time.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/surface_params.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::jobs {

// The cloud whole, or the parts it came in when its method streams them, so that it is never
// decoded whole.
struct SurfaceInput {
  core::PointCloud cloud;
  std::vector<core::ByteView> parts;  // Non-empty: the cloud is streamed from these; `cloud` is empty.
  int64_t points = 0;
  double diagonal = 0;  // Of the bounding box of all parts.
};

// Decodes and checks every part (against `limits`, the points of all parts together). Parts with
// normals whose points `streams` says go part by part are kept as they came; else they are
// joined. Errors: kInvalidArgument naming the part (undecodable, a mesh, bad points or normals,
// parts with and without normals), kResourceExhausted (over max_points).
absl::StatusOr<SurfaceInput> DecodeSurfaceInput(const Uploads& uploads, const PointParams& points,
                                                const InputLimits& limits,
                                                const std::function<bool(int64_t points)>& streams);

// The parts decoded in turn, each a chunk; they must outlive it.
class DracoPartsSource final : public pu::PointSource {
 public:
  explicit DracoPartsSource(const std::vector<core::ByteView>& parts) : parts_(parts) {}
  absl::Status ForEachChunk(const std::function<absl::Status(const core::PointCloud&)>& visit) const override;

 private:
  const std::vector<core::ByteView>& parts_;
};

}  // namespace lsqsurf::jobs
