#include "worker/jobs/pictures.h"

#include <spdlog/spdlog.h>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"
#include "worker/io/mesh_part.h"

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

absl::Status MeshPartPieces::ForEach(const std::function<absl::Status(const core::TriangleMesh&)>& visit) const {
  io::SelfContainedParts joiner(attribute_.empty() ? std::vector<std::string>{} : std::vector{attribute_});
  for (int64_t p = 0; p < parts_; ++p) {
    auto bytes = read_(p);
    if (!bytes.ok()) return bytes.status();
    auto part = io::DecodeMeshPart(*bytes);
    if (!part.ok()) {
      std::string why(part.status().message());
      constexpr std::string_view kDecoderPrefix = "mesh part: ";  // Numbered here instead.
      if (why.starts_with(kDecoderPrefix)) why.erase(0, kDecoderPrefix.size());
      return absl::InvalidArgumentError(core::StrCat("mesh part ", p, ": ", why));
    }
    *bytes = {};
    auto piece = joiner.Next(*part);
    if (!piece.ok()) return piece.status();
    LSQSURF_RETURN_IF_ERROR(visit(*piece));
  }
  return absl::OkStatus();
}

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

namespace {

// The renderer and view of a job's preview.
absl::StatusOr<std::pair<render::Renderer*, const render::RenderParams*>> PreviewRenderer(const PreviewSpec& preview,
                                                                                          RunEnvironment& env) {
  if (env.renderer == nullptr) return absl::UnavailableError("no renderer");
  auto renderer = env.renderer->Get();
  if (!renderer.ok()) return renderer.status();
  const auto* view = preview.view.As<render::RenderParams>();
  if (view == nullptr) return absl::InternalError("preview without view options");
  return std::make_pair(*renderer, view);
}

}  // namespace

absl::Status DrawPreview(const core::TriangleMesh& mesh, const PreviewSpec& preview, RunEnvironment& env) {
  LSQSURF_ASSIGN_OR_RETURN(auto drawing, PreviewRenderer(preview, env));
  auto png = PicturePng(*drawing.first, mesh, *drawing.second);
  if (!png.ok()) return png.status();
  return env.sink.Write(kPreviewArtifact, *png);
}

absl::Status DrawPreviewOfParts(int64_t parts, const PreviewSpec& preview, RunEnvironment& env) {
  LSQSURF_ASSIGN_OR_RETURN(auto drawing, PreviewRenderer(preview, env));
  const MeshPartPieces pieces(
      parts, [&env](int64_t part) { return env.sink.Read(MeshPartArtifact(part)); }, drawing.second->color_attribute);
  auto image = drawing.first->RenderMeshPieces(pieces, *drawing.second);
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return env.sink.Write(kPreviewArtifact, *png);
}

void PreviewFailures::Add(std::string_view picture, const absl::Status& why) {
  spdlog::warn("{} not drawn: {}", picture, why.message());
  if (++count_ <= 100) core::StrAppend(&reasons_, picture, ": ", why.message(), "\n");
}

absl::Status PreviewFailures::Report(RunEnvironment& env,
                                     std::vector<std::pair<std::string, double>>& statistics) const {
  if (count_ == 0) return absl::OkStatus();
  statistics.emplace_back("preview_failures", count_);
  return env.sink.Write(kPreviewErrorsArtifact, reasons_);
}

}  // namespace lsqsurf::jobs
