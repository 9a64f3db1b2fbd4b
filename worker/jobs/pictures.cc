#include "worker/jobs/pictures.h"

#include "worker/core/strings.h"
#include "worker/io/files.h"

namespace lsqsurf::jobs {
namespace {

absl::Status WritePng(const absl::StatusOr<render::Image>& image, const std::string& path) {
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  if (absl::Status s = io::WriteFileAtomically(path, *png); !s.ok()) {
    return absl::UnavailableError(core::StrCat("cannot write ", path, ": ", s.message()));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::string> PicturePng(render::Renderer& renderer, const core::TriangleMesh& mesh,
                                       const render::RenderParams& params) {
  auto image = renderer.RenderMesh(mesh, params);
  if (!image.ok()) return image.status();
  return render::EncodePng(*image);
}

absl::StatusOr<std::string> PicturePng(render::Renderer& renderer, const core::PointCloud& cloud,
                                       const render::RenderParams& params) {
  auto image = renderer.RenderPoints(cloud, params);
  if (!image.ok()) return image.status();
  return render::EncodePng(*image);
}

absl::Status WritePicture(render::Renderer& renderer, const core::TriangleMesh& mesh,
                          const render::RenderParams& params, const std::string& path) {
  return WritePng(renderer.RenderMesh(mesh, params), path);
}

absl::Status WritePicture(render::Renderer& renderer, const core::PointCloud& cloud, const render::RenderParams& params,
                          const std::string& path) {
  return WritePng(renderer.RenderPoints(cloud, params), path);
}

}  // namespace lsqsurf::jobs
