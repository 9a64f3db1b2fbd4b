// worker/jobs/pictures.h — PNG pictures of job results, written next to the other artifacts.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

// PNG bytes of the mesh (or the cloud). Errors: the renderer's.
absl::StatusOr<std::string> PicturePng(render::Renderer& renderer, const core::TriangleMesh& mesh,
                                       const render::RenderParams& params);
absl::StatusOr<std::string> PicturePng(render::Renderer& renderer, const core::PointCloud& cloud,
                                       const render::RenderParams& params);

// Draws the mesh (or the cloud) and writes the PNG atomically to `path`. Errors: the renderer's,
// or kUnavailable when the file cannot be written.
absl::Status WritePicture(render::Renderer& renderer, const core::TriangleMesh& mesh,
                          const render::RenderParams& params, const std::string& path);
absl::Status WritePicture(render::Renderer& renderer, const core::PointCloud& cloud, const render::RenderParams& params,
                          const std::string& path);

}  // namespace lsqsurf::jobs
