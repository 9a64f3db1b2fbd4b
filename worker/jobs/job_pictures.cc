#include "worker/jobs/job_pictures.h"

#include <algorithm>

#include "absl/cleanup/cleanup.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/job_service_internal.h"
#include "worker/jobs/pictures.h"
#include "worker/jobs/volume_job.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

JobPictures::JobPictures(const JobTable& table, BlobStore& blobs, int max_renders, int64_t max_render_bytes)
    : table_(table),
      blobs_(blobs),
      max_renders_(max_renders),
      renderer_(std::make_unique<render::SharedRenderer>()),
      slots_(max_renders),
      volume_pictures_(std::make_unique<VolumePictures>(max_render_bytes)) {}

JobPictures::~JobPictures() = default;

bool JobPictures::TakeSlot(const std::string& owner) {
  std::lock_guard lock(slots_mutex_);
  return slots_.TryTake(owner) == core::FairSlots::Refusal::kNone;
}

void JobPictures::ReleaseSlot(const std::string& owner) {
  std::lock_guard lock(slots_mutex_);
  slots_.Release(owner);
}

absl::StatusOr<RenderedPicture> JobPictures::Render(const std::string& owner, const JobRecord& record,
                                                    const std::string& name, const core::ParamSet& view,
                                                    const core::JobContext* ctx) {
  const std::string& id = record.id;
  const auto* params = view.As<render::RenderParams>();
  if (params == nullptr) return absl::InternalError("view options of another type");
  // Checked before any file is read or a context is made.
  LSQSURF_RETURN_IF_ERROR(render::Validate(*params));
  if (!TakeSlot(owner)) {
    return absl::ResourceExhaustedError(core::StrCat("the pictures this server draws at once (", max_renders_,
                                                     ", half of them per user) are being drawn; "
                                                     "try again shortly"));
  }
  const absl::Cleanup release = [&] { ReleaseSlot(owner); };
  const bool whole_name = name.empty() && !record.results.empty();
  // A part stands for the whole mesh only where it is one of the job's results; other names get
  // OpenResult's answer.
  const bool listed =
      whole_name || std::find(record.results.begin(), record.results.end(), name) != record.results.end();
  if (listed && MeshPartOf(whole_name ? record.results.front() : name) >= 0) {
    return RenderMeshParts(record, *params);
  }
  auto reader = OpenJobResult(table_, blobs_, id, name);
  if (!reader.ok()) return reader.status();
  auto read = ReadAll(**reader);
  if (!read.ok()) return read.status();
  const std::string& bytes = *read;
  if (volume::IsStoredVolumeField(bytes)) return RenderVolumeField(id, bytes, *params, ctx);
  auto geometry = io::PeekDracoGeometry(bytes);
  if (!geometry.ok()) {
    return absl::InvalidArgumentError(
        core::StrCat("artifact '", name, "' is not a Draco mesh or point set; only those can be rendered"));
  }
  auto renderer = renderer_->Get();
  if (!renderer.ok()) return renderer.status();
  render::RenderInfo info;
  absl::StatusOr<render::Image> image = absl::InvalidArgumentError("");
  if (*geometry == io::DracoGeometry::kTriangleMesh) {
    auto mesh = io::DecodeDracoMesh(bytes);
    if (!mesh.ok()) return mesh.status();
    image = (*renderer)->RenderMesh(*mesh, *params, &info);
  } else {
    auto cloud = io::DecodeDracoPointCloud(bytes);
    if (!cloud.ok()) return cloud.status();
    image = (*renderer)->RenderPoints(*cloud, *params, &info);
  }
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return RenderedPicture{*std::move(png), info.color_min, info.color_max, info.renderer, 0, 0, info.samples};
}

absl::StatusOr<RenderedPicture> JobPictures::RenderMeshParts(const JobRecord& record,
                                                             const render::RenderParams& params) {
  // Every part listed when the call came: of a running job, the surface done so far.
  int64_t parts = 0;
  while (std::find(record.results.begin(), record.results.end(), MeshPartArtifact(parts)) != record.results.end()) {
    ++parts;
  }
  const MeshPartPieces pieces(
      parts,
      [&](int64_t part) -> absl::StatusOr<std::string> {
        auto reader = OpenJobResult(table_, blobs_, record.id, MeshPartArtifact(part));
        if (!reader.ok()) return reader.status();
        return ReadAll(**reader);
      },
      params.color_attribute);
  auto renderer = renderer_->Get();
  if (!renderer.ok()) return renderer.status();
  render::RenderInfo info;
  auto image = (*renderer)->RenderMeshPieces(pieces, params, &info);
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return RenderedPicture{*std::move(png), info.color_min, info.color_max, info.renderer};
}

absl::StatusOr<RenderedPicture> JobPictures::RenderVolumeField(const std::string& id, const std::string& bytes,
                                                               const render::RenderParams& params,
                                                               const core::JobContext* ctx) {
  LSQSURF_ASSIGN_OR_RETURN(VolumePicture picture, volume_pictures_->Draw(id, bytes, params, *renderer_, ctx));
  return RenderedPicture{std::move(picture.png), picture.info.color_min, picture.info.color_max, picture.info.renderer,
                         picture.grid_rms_error, picture.grid_max_error, picture.info.samples};
}

absl::Status JobPictures::RendererStatus() { return renderer_->Get().status(); }

}  // namespace lsqsurf::jobs
