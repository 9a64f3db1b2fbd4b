// worker/jobs/pictures.h — PNG pictures of job results, written next to the other artifacts.
#pragma once

#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/jobs/job_kind.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

// The picture a job draws of its result when asked (JobSpec::preview).
inline constexpr char kPreviewArtifact[] = "preview.png";
// Why pictures a job promised were not drawn, a line each ("preview.png: <reason>").
inline constexpr char kPreviewErrorsArtifact[] = "preview-errors.txt";

// PNG bytes of the mesh (or the cloud). Errors: the renderer's.
absl::StatusOr<std::string> PicturePng(render::Renderer& renderer, const core::TriangleMesh& mesh,
                                       const render::RenderParams& params);
absl::StatusOr<std::string> PicturePng(render::Renderer& renderer, const core::PointCloud& cloud,
                                       const render::RenderParams& params);

// The parts of a mesh delivered in parts (io/mesh_part.h) as pieces to draw: each part with the
// vertices of earlier parts its faces name (io::SelfContainedParts, carrying only the attribute
// named `attribute`, if any).
class MeshPartPieces final : public render::MeshPieces {
 public:
  // The bytes of part `part` (0, 1, ...). Errors: its own.
  using ReadPart = std::function<absl::StatusOr<std::string>(int64_t part)>;
  MeshPartPieces(int64_t parts, ReadPart read, std::string attribute)
      : parts_(parts), read_(std::move(read)), attribute_(std::move(attribute)) {}
  // Errors: those of `read`, kInvalidArgument (a part that does not decode or does not follow on
  // from the ones before it, naming it), and those of `visit`.
  absl::Status ForEach(const std::function<absl::Status(const core::TriangleMesh&)>& visit) const override;

 private:
  int64_t parts_;
  ReadPart read_;
  std::string attribute_;
};

// Draws the mesh (or the cloud) and writes the PNG atomically to `path`. Errors: the renderer's,
// or kUnavailable when the file cannot be written.
absl::Status WritePicture(render::Renderer& renderer, const core::TriangleMesh& mesh,
                          const render::RenderParams& params, const std::string& path);
absl::Status WritePicture(render::Renderer& renderer, const core::PointCloud& cloud, const render::RenderParams& params,
                          const std::string& path);

// A job's preview of its mesh, written to kPreviewArtifact through env.sink. Errors: kUnavailable
// (no renderer), the renderer's, the sink's.
absl::Status DrawPreview(const core::TriangleMesh& mesh, const PreviewSpec& preview, RunEnvironment& env);
// The same of a mesh this run wrote in `parts` parts (MeshPartArtifact), read back one at a time.
absl::Status DrawPreviewOfParts(int64_t parts, const PreviewSpec& preview, RunEnvironment& env);

// A picture that failed does not fail its job, whose mesh or frames are what it is for; it is
// logged, counted in the statistic preview_failures and its reason kept in
// kPreviewErrorsArtifact (at most the first 100 reasons), so that the user sees why.
class PreviewFailures {
 public:
  void Add(std::string_view picture, const absl::Status& why);
  // Writes the reasons and the count into `statistics`; nothing when none failed.
  absl::Status Report(RunEnvironment& env, std::vector<std::pair<std::string, double>>& statistics) const;

 private:
  int count_ = 0;
  std::string reasons_;
};

}  // namespace lsqsurf::jobs
