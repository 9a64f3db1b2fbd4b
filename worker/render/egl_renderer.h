// worker/render/egl_renderer.h — the EGL backend of worker/render: one OpenGL 4.5 core context,
// owned by a render thread. egl_renderer.cc holds the context, the thread and the programs;
// egl_mesh_pass.cc draws meshes and points; egl_volume_pass.cc ray-casts volumes. Included by
// those files only.
#pragma once

#include <EGL/egl.h>
#include <EGL/eglext.h>

#include <array>
#include <condition_variable>
#include <deque>
#include <functional>
#include <future>
#include <mutex>
#include <span>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "worker/render/face_culling.h"
#include "worker/render/gl_api.h"
#include "worker/render/render.h"
#include "worker/render/view.h"

namespace lsqsurf::render::internal {

// Geometry handed to the GL: positions, optional normals and scalars, optional triangles, and
// what the caller's thread worked out about them (the render thread only draws).
struct Drawable {
  std::span<const core::Vec3f> positions, normals;
  std::span<const float> scalars;
  std::span<const core::Triangle> faces;  // Empty: points.
  core::Box3 box{};
  OutsideWinding winding = OutsideWinding::kUnknown;
};

class EglRenderer final : public Renderer {
 public:
  static absl::StatusOr<std::unique_ptr<Renderer>> Create();

  ~EglRenderer() override;

  absl::StatusOr<Image> RenderMesh(const core::TriangleMesh& mesh, const RenderParams& params,
                                   RenderInfo* info) override;

  absl::StatusOr<Image> RenderPoints(const core::PointCloud& cloud, const RenderParams& params,
                                     RenderInfo* info) override;

  absl::StatusOr<Image> RenderMeshPieces(const MeshPieces& pieces, const RenderParams& params,
                                         RenderInfo* info) override;

  absl::StatusOr<Image> RenderVolume(const VolumeGrid& grid, const RenderParams& params, RenderInfo* info) override;

  std::string description() const override { return description_; }

 private:
  EglRenderer() = default;

  // The attribute `name` colours by; for "rgb" (the vertices' own colour) red, green and blue
  // packed as r·65536 + g·256 + b, exact in a float, into `packed`.
  static absl::StatusOr<std::span<const float>> FindScalars(const std::vector<core::ScalarAttribute>& attributes,
                                                            const std::string& name, std::vector<float>& packed);

  // Measures the geometry on the calling thread, then draws it on the render thread.
  absl::StatusOr<Image> Enqueue(Drawable d, const RenderParams& params, RenderInfo* info);

  // Runs `work` on the render thread and waits for it.
  absl::StatusOr<Image> Run(std::function<absl::StatusOr<Image>()> work);

  void Loop(std::promise<absl::Status>& ready);

  // The EGL device platform first (NVIDIA's headless path; Mesa exposes its software device
  // the same way), then Mesa's surfaceless platform.
  absl::Status InitContext();

  bool TryDisplay(EGLDisplay display, const std::string& what, std::string& tried);

  absl::StatusOr<GLuint> Compile(const char* vertex, const char* fragment);

  absl::Status InitPrograms();

  void Shutdown();

  // Multisampled colour + depth, resolved into a single-sample colour buffer.
  struct Targets {
    GLuint fbo[2] = {}, rbo[3] = {};
    int samples = 1;  // What the GL granted per pixel.
  };
  // `samples` is capped at the most the GL offers (GL_MAX_SAMPLES); one sample is a plain
  // buffer, since a GL may round a multisampled request for one up to its smallest count.
  absl::StatusOr<Targets> MakeTargets(int w, int h, int samples);
  void ReleaseTargets(Targets& t);

  // Uploads the vertex attributes into `buffers` (positions, normals, scalars) of the bound VAO.
  void UploadAttributes(const Drawable& d, const GLuint* buffers, bool has_normals, bool colour);

  // The surface program with the view, shading and colour map of this picture.
  void SetUniforms(const RenderParams& p, const View& view, double lo, double span, bool has_normals, bool colour);

  void DrawFaces(const Drawable& d, const RenderParams& p, const View& view, GLuint index_buffer);

  void DrawPoints(const Drawable& d, const RenderParams& p, const View& view);

  // Resolves the samples and reads the picture back, top row first; the GL's error, if any.
  Image ReadBack(const Targets& t, int w, int h, GLenum* error);

  // One picture in the making: its render targets, view and colour range. Render-thread only:
  // BeginPicture clears the targets, DrawInto adds geometry, FinishPicture reads the image back
  // and releases the targets.
  struct Picture {
    Targets targets;
    View view;
    double lo = 0, hi = 0;
    bool coloured = false;
  };
  absl::StatusOr<Picture> BeginPicture(const core::Box3& box, const RenderParams& p, double lo, double hi);
  void DrawInto(const Drawable& d, const RenderParams& p, const Picture& picture);
  absl::StatusOr<Image> FinishPicture(Picture& picture, const RenderParams& p, RenderInfo* info);

  // Render-thread only.
  absl::StatusOr<Image> Draw(const Drawable& d, const RenderParams& p, RenderInfo* info);

  // Render-thread only.
  absl::StatusOr<Image> DrawVolume(const VolumeGrid& g, const std::vector<float>& texels,
                                   const std::vector<std::array<double, 2>>& opacity, std::pair<double, double> range,
                                   const RenderParams& p, RenderInfo* info);

  void SetVolumeUniforms(const VolumeGrid& g, const core::Box3& box, const std::vector<std::array<double, 2>>& opacity,
                         std::pair<double, double> range, const RenderParams& p);

  // A vertical colour bar at the right edge, maximum on top, with its bounds printed beside it.
  void DrawLegend(int w, int h, double lo, double hi);

  internal::GlApi gl_;
  EGLDisplay display_ = EGL_NO_DISPLAY;
  EGLContext context_ = EGL_NO_CONTEXT;
  GLuint surface_program_ = 0, overlay_program_ = 0, volume_program_ = 0, colormap_ = 0;
  std::string renderer_, description_;
  int max_samples_ = 1;  // GL_MAX_SAMPLES of the context.

  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<std::packaged_task<absl::StatusOr<Image>()>> tasks_;
  bool stopping_ = false;
};

}  // namespace lsqsurf::render::internal
