// worker/render/render.h — headless pictures of meshes and point clouds.
//
// A Renderer draws one mesh or point cloud per call into an RGBA image. Backends are chosen by
// name: "egl" (OpenGL 4.5 core through EGL: the EGL device platform first, preferring an NVIDIA
// device over Mesa's software one, then Mesa's surfaceless platform) and "auto" (the best
// available, today the same). A renderer is safe to call from many threads: the EGL backend owns
// its context on one render thread and serves calls in order.
//
// Conventions: the camera looks at the centre of the model's bounding box (or of a given box)
// from the direction given by azimuth and elevation about the up axis: with +z up, azimuth turns
// from +x towards +y; with +y up, from +z towards +x; with +x up, from +y towards +z (always the
// next two axes in cyclic order). The up axis points up in the picture. The key light comes from
// the camera, turned 25° up and 25° left.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/params.h"

namespace lsqsurf::render {

inline constexpr int kMaxImageSide = 4096;

enum class UpAxis { kX, kY, kZ };

struct Camera {
  UpAxis up = UpAxis::kZ;       // Scanned models are often y-up (e.g. the Spot and bunny data).
  double azimuth_deg = 35.0;    // Around the up axis (see the conventions above).
  double elevation_deg = 25.0;  // Above the plane normal to the up axis, −89..89.
  double distance = 0.0;        // From the box centre, model units; 0 = frame the bounding sphere.
  double fov_deg = 30.0;        // Vertical field of view, 5..120.
  // The region to frame and aim at; empty (the default) = the model's bounding box. A fixed
  // box keeps the scale of a sequence of frames constant.
  core::Box3 framing_box;
};

// "x", "y" or "z" (also "+x" … ); kInvalidArgument otherwise.
absl::StatusOr<UpAxis> ParseUpAxis(std::string_view name);

enum class Shading { kSmooth, kFlat };

// How a scalar field on a grid is drawn: direct volume rendering (front-to-back compositing of
// the colour map and the opacity transfer function) or the first crossing of an iso-value.
enum class VolumeMode { kDirect = 0, kIsosurface = 1 };

// The colour attribute that draws the vertices' own colour (attributes red, green, blue).
inline constexpr char kTrueColour[] = "rgb";

struct RenderParams {
  int width = 1024, height = 1024;  // 16..kMaxImageSide.
  Camera camera;
  Shading shading = Shading::kSmooth;
  bool wireframe = false;    // Dark edges over the shaded faces.
  int samples = 4;           // MSAA samples per pixel: 1, 2, 4 or 8 (at most what the GL offers).
  bool transparent = false;  // Background alpha 0 instead of `background`.
  std::array<float, 3> background = {1.0f, 1.0f, 1.0f};
  std::array<float, 3> base_color = {0.78f, 0.80f, 0.84f};  // Without a colour attribute.
  double specular = 0.25;  // Blinn–Phong highlight strength, 0..1 (0 = Lambert only).
  // Name of a per-vertex (or per-point) scalar to colour through the colour map; empty = none;
  // kTrueColour: the vertices' own colour (red, green, blue 0..255), without a legend. The map
  // spans [color_min, color_max]; equal bounds (the default) mean the data's range.
  std::string color_attribute;
  double color_min = 0, color_max = 0;
  bool legend = true;     // A colour bar with its bounds, when colouring.
  double point_size = 0;  // Splat diameter in pixels for clouds; 0 = from the spacing.
  // Volume fields only.
  VolumeMode volume_mode = VolumeMode::kDirect;
  // Opacity transfer function: "t:alpha" pairs separated by commas, t in [0, 1] over the colour
  // range, alpha the opacity one grid cell of travel gathers at that value (linear between).
  std::string opacity = "0:0,0.5:0.05,1:0.4";
  double iso_value = 0;        // kIsosurface: the level.
  int volume_resolution = 96;  // Grid points along the longest side of the field's box.
  double ray_step = 0.5;       // Ray-marching step, in grid cells.
};

// A scalar field sampled on a regular grid (x fastest), with its gradient; NaN values mark
// points outside the data's domain (rays pass them as empty space).
struct VolumeGrid {
  std::array<int, 3> dims = {0, 0, 0};
  core::Vec3d origin = core::Vec3d::Zero();
  core::Vec3d spacing = core::Vec3d::Ones();
  std::vector<float> values;
  std::vector<core::Vec3f> gradients;
};

// The view options users set (size, camera, colouring, shading): the one description of them,
// which the service's RenderOptions mirror by name. Background, specular, legend, point size
// and the framing box are set by code, not users.
const core::ParamTable<RenderParams>& ViewParamTable();
// The table's checks, then those of the fields only code sets.
absl::Status Validate(const RenderParams& params);

struct Image {
  int width = 0, height = 0;
  std::vector<uint8_t> rgba;  // Row-major from the top row, 4 bytes per pixel.

  std::array<uint8_t, 4> At(int x, int y) const {
    const size_t i = 4 * (static_cast<size_t>(y) * static_cast<size_t>(width) + static_cast<size_t>(x));
    return {rgba[i], rgba[i + 1], rgba[i + 2], rgba[i + 3]};
  }
};

// Where the picture's colour bar and its range came from (for callers that report them).
struct RenderInfo {
  double color_min = 0, color_max = 0;
  std::string renderer;  // The GL renderer string, e.g. "llvmpipe (LLVM 15.0.6, 256 bits)".
  // Samples per pixel the picture was drawn with: the request's, or the most the GL offers
  // when it offers fewer (llvmpipe: 4); 1 for pictures that are not multisampled.
  int samples = 1;
};

// Draws `grid` with the camera, size, background and volume options of `params`, on the CPU
// (all cores): rays through pixel centres, trilinear samples every `ray_step` cells, shading
// by the interpolated gradient. The reference the GL path will be measured against.
// Errors: kInvalidArgument (bad parameters or opacity text, an empty or inconsistent grid).
absl::StatusOr<Image> RaycastVolume(const VolumeGrid& grid, const RenderParams& params, RenderInfo* info = nullptr);

// The trilinear value of `grid` at x; NaN outside the grid or next to a point outside the data.
double GridValue(const VolumeGrid& grid, const core::Vec3d& x);

// The (t, alpha) points of an opacity text. Errors: kInvalidArgument naming the bad entry.
absl::StatusOr<std::vector<std::array<double, 2>>> ParseOpacity(std::string_view text);

// A mesh too large to hold at once, handed over in pieces: each a mesh of its own (its faces in
// its own vertex numbers), the same pieces in the same order on every call.
class MeshPieces {
 public:
  virtual ~MeshPieces() = default;
  // Calls `visit` with each piece in turn; stops at the first error either returns.
  virtual absl::Status ForEach(const std::function<absl::Status(const core::TriangleMesh&)>& visit) const = 0;
};

class Renderer {
 public:
  virtual ~Renderer() = default;
  // Errors: kInvalidArgument (bad parameters, an empty mesh, an unknown colour attribute),
  // kResourceExhausted (the GL could not allocate the image), kInternal (a GL failure).
  virtual absl::StatusOr<Image> RenderMesh(const core::TriangleMesh& mesh, const RenderParams& params,
                                           RenderInfo* info = nullptr) = 0;
  virtual absl::StatusOr<Image> RenderPoints(const core::PointCloud& cloud, const RenderParams& params,
                                             RenderInfo* info = nullptr) = 0;
  // The picture RenderMesh draws of the pieces joined (framed on their joint box, coloured over
  // their joint range, no faces culled), holding one piece at a time: the pieces are read once on
  // the calling thread to frame them, then again on the render thread to draw them one after
  // another into the same image. Errors: those of RenderMesh (no triangles in any piece, an
  // attribute one of them lacks), and the pieces' own.
  virtual absl::StatusOr<Image> RenderMeshPieces(const MeshPieces& pieces, const RenderParams& params,
                                                 RenderInfo* info = nullptr) = 0;
  // The picture RaycastVolume draws, ray-cast in a fragment shader over 3-D textures of the
  // grid's values and gradients. Errors: those of RaycastVolume, kResourceExhausted (the grid
  // does not fit in the GL's memory).
  virtual absl::StatusOr<Image> RenderVolume(const VolumeGrid& grid, const RenderParams& params,
                                             RenderInfo* info = nullptr) = 0;
  virtual std::string description() const = 0;  // Backend, EGL platform and GL renderer.
};

// "egl" or "auto". Errors: kInvalidArgument (unknown name), kUnavailable (no usable EGL display
// or OpenGL 4.5 context, with what was tried).
absl::StatusOr<std::unique_ptr<Renderer>> CreateRenderer(std::string_view backend = "auto");

// A renderer made on first use and shared by its callers: a context costs about 0.1 s and
// many processes never draw. A failed creation is retried by the next call. Thread-safe.
class SharedRenderer {
 public:
  explicit SharedRenderer(std::string backend = "auto") : backend_(std::move(backend)) {}
  // Errors: those of CreateRenderer.
  absl::StatusOr<Renderer*> Get();

 private:
  std::string backend_;
  std::mutex mutex_;
  std::unique_ptr<Renderer> renderer_;
};

// The colour map (perceptually ordered, dark blue → green → yellow) at t in [0, 1], as RGB in
// [0, 1]; the renderer's shader samples the same table.
std::array<float, 3> ColorMap(double t);

// PNG bytes of the image (RGBA, 8 bits). Errors: kInvalidArgument (empty image), kInternal.
absl::StatusOr<std::string> EncodePng(const Image& image);

}  // namespace lsqsurf::render
