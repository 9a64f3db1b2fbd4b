// The EGL backend of worker/render: the context and its thread, the programs, and what the
// public calls check before they queue work for that thread.
#include "worker/render/egl_renderer.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#if defined(__SANITIZE_ADDRESS__)
#include <sanitizer/lsan_interface.h>
#endif

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/render/egl_shaders.h"

namespace lsqsurf::render {
namespace internal {

std::string GlApi::Load() {
#define LSQSURF_GL_LOAD(name, upper)                                          \
  name = reinterpret_cast<PFNGL##upper##PROC>(eglGetProcAddress("gl" #name)); \
  if (name == nullptr) return "gl" #name;
  LSQSURF_GL_FUNCTIONS(LSQSURF_GL_LOAD)
#undef LSQSURF_GL_LOAD
  return "";
}

absl::StatusOr<std::unique_ptr<Renderer>> EglRenderer::Create() {
  std::unique_ptr<EglRenderer> r(new EglRenderer());
  std::promise<absl::Status> ready;
  auto started = ready.get_future();
  r->thread_ = std::thread([raw = r.get(), &ready] { raw->Loop(ready); });
  if (absl::Status s = started.get(); !s.ok()) return s;
  return std::unique_ptr<Renderer>(std::move(r));
}

EglRenderer::~EglRenderer() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

absl::StatusOr<Image> EglRenderer::RenderMesh(const core::TriangleMesh& mesh, const RenderParams& params,
                                              RenderInfo* info) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (mesh.faces.empty()) return absl::InvalidArgumentError("the mesh has no triangles to draw");
  std::vector<float> packed;
  auto scalars = FindScalars(mesh.vertex_attributes, params.color_attribute, packed);
  if (!scalars.ok()) return scalars.status();
  return Enqueue({mesh.vertices, mesh.normals, *scalars, mesh.faces}, params, info);
}

absl::StatusOr<Image> EglRenderer::RenderPoints(const core::PointCloud& cloud, const RenderParams& params,
                                                RenderInfo* info) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (cloud.positions.empty()) return absl::InvalidArgumentError("the point cloud is empty");
  std::vector<float> packed;
  auto scalars = FindScalars(cloud.attributes, params.color_attribute, packed);
  if (!scalars.ok()) return scalars.status();
  return Enqueue({cloud.positions, cloud.normals, *scalars, {}}, params, info);
}

absl::StatusOr<Image> EglRenderer::RenderMeshPieces(const MeshPieces& pieces, const RenderParams& params,
                                                    RenderInfo* info) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  // First pass: the joint box and colour range, and whether there is anything to draw.
  core::Box3 box;
  int64_t faces = 0;
  double lo = params.color_min, hi = params.color_max;
  const bool data_range = lo == hi;
  if (data_range) lo = INFINITY, hi = -INFINITY;
  LSQSURF_RETURN_IF_ERROR(pieces.ForEach([&](const core::TriangleMesh& piece) -> absl::Status {
    if (piece.faces.empty()) return absl::OkStatus();
    std::vector<float> packed;
    auto scalars = FindScalars(piece.vertex_attributes, params.color_attribute, packed);
    if (!scalars.ok()) return scalars.status();
    box.extend(core::BoundingBox(piece.vertices));
    faces += static_cast<int64_t>(piece.faces.size());
    if (data_range && !scalars->empty()) {
      const auto [mn, mx] = std::minmax_element(scalars->begin(), scalars->end());
      lo = std::min(lo, static_cast<double>(*mn));
      hi = std::max(hi, static_cast<double>(*mx));
    }
    return absl::OkStatus();
  }));
  if (faces == 0) return absl::InvalidArgumentError("the mesh has no triangles to draw");
  if (lo > hi) lo = hi = 0;  // Not coloured.
  return Run([&]() -> absl::StatusOr<Image> {
    auto picture = BeginPicture(box, params, lo, hi);
    if (!picture.ok()) return picture.status();
    picture->coloured = !params.color_attribute.empty();
    const absl::Status drawn = pieces.ForEach([&](const core::TriangleMesh& piece) -> absl::Status {
      if (piece.faces.empty()) return absl::OkStatus();
      std::vector<float> packed;
      auto scalars = FindScalars(piece.vertex_attributes, params.color_attribute, packed);
      if (!scalars.ok()) return scalars.status();
      // Pieces are open: every face is drawn, two-sided.
      DrawInto({piece.vertices, piece.normals, *scalars, piece.faces, box}, params, *picture);
      // A software rasterizer may hold a frame's binned triangles until the image is read back;
      // finishing each piece bounds that by one piece.
      gl_.Finish();
      return absl::OkStatus();
    });
    auto image = FinishPicture(*picture, params, info);
    if (!drawn.ok()) return drawn;
    return image;
  });
}

absl::StatusOr<Image> EglRenderer::RenderVolume(const VolumeGrid& grid, const RenderParams& params, RenderInfo* info) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  const size_t count = static_cast<size_t>(grid.dims[0]) * grid.dims[1] * grid.dims[2];
  if (grid.dims[0] < 2 || grid.dims[1] < 2 || grid.dims[2] < 2 || grid.values.size() != count ||
      grid.gradients.size() != count) {
    return absl::InvalidArgumentError("the volume grid is empty or its arrays do not match its size");
  }
  LSQSURF_ASSIGN_OR_RETURN(auto opacity, ParseOpacity(params.opacity));
  if (opacity.size() > static_cast<size_t>(kMaxOpacityPoints)) {
    return absl::InvalidArgumentError(core::StrCat("opacity: at most ", kMaxOpacityPoints, " points"));
  }
  // Texels of (value, gradient), interleaved on the calling thread.
  std::vector<float> texels(4 * count);
  for (size_t i = 0; i < count; ++i) {
    texels[4 * i] = grid.values[i];
    for (int c = 0; c < 3; ++c) texels[4 * i + 1 + c] = grid.gradients[i][c];
  }
  const auto range = internal::VolumeColorRange(grid, params);
  return Run([&] { return DrawVolume(grid, texels, opacity, range, params, info); });
}

absl::StatusOr<std::span<const float>> EglRenderer::FindScalars(const std::vector<core::ScalarAttribute>& attributes,
                                                                const std::string& name, std::vector<float>& packed) {
  if (name.empty()) return std::span<const float>();
  if (name == kTrueColour) {
    const size_t n = attributes.empty() ? 0 : attributes.front().values.size();
    const auto channel = core::ColourChannels(attributes, n);
    if (channel[0] == nullptr) {
      return absl::InvalidArgumentError("color=rgb needs the attributes red, green and blue; this result has none");
    }
    packed.resize(n);
    for (size_t i = 0; i < n; ++i) packed[i] = static_cast<float>(core::PackedColour(channel, i));
    return std::span<const float>(packed);
  }
  std::string known;
  for (const core::ScalarAttribute& a : attributes) {
    if (a.name == name) return std::span<const float>(a.values);
    known += (known.empty() ? "" : ", ") + a.name;
  }
  return absl::InvalidArgumentError(
      core::StrCat("no attribute '", name, "' to colour by; this result has: ", known.empty() ? "none" : known));
}

absl::StatusOr<Image> EglRenderer::Enqueue(Drawable d, const RenderParams& params, RenderInfo* info) {
  d.box = core::BoundingBox(d.positions);
  if (!d.faces.empty()) d.winding = ClosedMeshOutsideWinding(d.positions, d.normals, d.faces);
  return Run([&] { return Draw(d, params, info); });
}

absl::StatusOr<Image> EglRenderer::Run(std::function<absl::StatusOr<Image>()> work) {
  std::packaged_task<absl::StatusOr<Image>()> task(std::move(work));
  auto result = task.get_future();
  {
    std::lock_guard lock(mutex_);
    tasks_.push_back(std::move(task));
  }
  wake_.notify_one();
  return result.get();
}

void EglRenderer::Loop(std::promise<absl::Status>& ready) {
#if defined(__SANITIZE_ADDRESS__)
  // Mesa keeps its EGL device list, and caches that hang off it, for the life of the process;
  // the leak checker of sanitizer builds would report them at exit. Only this thread's
  // allocations are exempt, and the code it runs holds its own memory in RAII containers.
  __lsan::ScopedDisabler driver_globals;
#endif
  absl::Status s = InitContext();
  if (s.ok()) s = InitPrograms();
  const bool ok = s.ok();
  ready.set_value(std::move(s));
  if (!ok) {
    Shutdown();
    return;
  }
  for (;;) {
    std::packaged_task<absl::StatusOr<Image>()> task;
    {
      std::unique_lock lock(mutex_);
      wake_.wait(lock, [&] { return stopping_ || !tasks_.empty(); });
      if (tasks_.empty()) break;
      task = std::move(tasks_.front());
      tasks_.pop_front();
    }
    task();
  }
  Shutdown();
}

absl::Status EglRenderer::InitContext() {
  std::string tried;
  auto query_devices = reinterpret_cast<PFNEGLQUERYDEVICESEXTPROC>(eglGetProcAddress("eglQueryDevicesEXT"));
  auto device_string = reinterpret_cast<PFNEGLQUERYDEVICESTRINGEXTPROC>(eglGetProcAddress("eglQueryDeviceStringEXT"));
  auto platform_display =
      reinterpret_cast<PFNEGLGETPLATFORMDISPLAYEXTPROC>(eglGetProcAddress("eglGetPlatformDisplayEXT"));
  if (platform_display == nullptr)
    return absl::UnavailableError("EGL has no eglGetPlatformDisplayEXT: no headless display possible");
  std::vector<std::pair<int, EGLDeviceEXT>> ranked;
  if (query_devices != nullptr && device_string != nullptr) {
    EGLDeviceEXT devices[16];
    EGLint count = 0;
    if (query_devices(16, devices, &count) == EGL_TRUE) {
      for (EGLint i = 0; i < count; ++i) {
        const char* ext = device_string(devices[i], EGL_EXTENSIONS);
        const std::string extensions = ext ? ext : "";
        const int rank = extensions.find("EGL_NV_device_cuda") != std::string::npos         ? 0
                         : extensions.find("EGL_MESA_device_software") == std::string::npos ? 1
                                                                                            : 2;
        ranked.emplace_back(rank, devices[i]);
      }
    }
  }
  std::stable_sort(ranked.begin(), ranked.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  for (const auto& [rank, device] : ranked) {
    static constexpr const char* kKinds[] = {"NVIDIA device", "GPU device", "software device"};
    if (TryDisplay(platform_display(EGL_PLATFORM_DEVICE_EXT, device, nullptr), core::StrCat("EGL ", kKinds[rank]),
                   tried)) {
      return absl::OkStatus();
    }
  }
  if (TryDisplay(platform_display(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr), "Mesa surfaceless",
                 tried)) {
    return absl::OkStatus();
  }
  return absl::UnavailableError(
      core::StrCat("no OpenGL 4.5 context through EGL (tried: ", tried.empty() ? "no EGL devices or platforms" : tried,
                   "); install Mesa (libegl-mesa0, libgl1-mesa-dri) or a GPU driver"));
}

bool EglRenderer::TryDisplay(EGLDisplay display, const std::string& what, std::string& tried) {
  auto fail = [&](const char* step) {
    tried +=
        core::StrCat(tried.empty() ? "" : "; ", what, ": ", step, " failed (0x", std::to_string(eglGetError()), ")");
    if (display != EGL_NO_DISPLAY) eglTerminate(display);
    return false;
  };
  if (display == EGL_NO_DISPLAY) return fail("display");
  EGLint major = 0, minor = 0;
  if (eglInitialize(display, &major, &minor) != EGL_TRUE) return fail("eglInitialize");
  if (eglBindAPI(EGL_OPENGL_API) != EGL_TRUE) return fail("eglBindAPI(OpenGL)");
  const EGLint config_attributes[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_NONE};
  EGLConfig config = nullptr;
  EGLint configs = 0;
  if (eglChooseConfig(display, config_attributes, &config, 1, &configs) != EGL_TRUE || configs == 0) {
    config = nullptr;  // EGL_KHR_no_config_context: the context renders into FBOs only.
  }
  const EGLint context_attributes[] = {
      EGL_CONTEXT_MAJOR_VERSION,           4,       EGL_CONTEXT_MINOR_VERSION, 5, EGL_CONTEXT_OPENGL_PROFILE_MASK,
      EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL_NONE};
  EGLContext context = eglCreateContext(display, config, EGL_NO_CONTEXT, context_attributes);
  if (context == EGL_NO_CONTEXT) return fail("OpenGL 4.5 core context");
  if (eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, context) != EGL_TRUE) {
    eglDestroyContext(display, context);
    return fail("eglMakeCurrent without a surface");
  }
  if (const std::string missing = gl_.Load(); !missing.empty()) {
    eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
    eglDestroyContext(display, context);
    return fail(core::StrCat("loading ", missing).c_str());
  }
  display_ = display;
  context_ = context;
  const auto* renderer = reinterpret_cast<const char*>(gl_.GetString(GL_RENDERER));
  renderer_ = renderer ? renderer : "unknown";
  gl_.GetIntegerv(GL_MAX_SAMPLES, &max_samples_);
  max_samples_ = std::max(1, max_samples_);
  description_ = core::StrCat("egl (", what, "): ", renderer_);
  return true;
}

absl::StatusOr<GLuint> EglRenderer::Compile(const char* vertex, const char* fragment) {
  GLuint shaders[2] = {gl_.CreateShader(GL_VERTEX_SHADER), gl_.CreateShader(GL_FRAGMENT_SHADER)};
  const char* sources[2] = {vertex, fragment};
  const GLuint program = gl_.CreateProgram();
  std::string log;
  for (int i = 0; i < 2; ++i) {
    gl_.ShaderSource(shaders[i], 1, &sources[i], nullptr);
    gl_.CompileShader(shaders[i]);
    GLint ok = 0;
    gl_.GetShaderiv(shaders[i], GL_COMPILE_STATUS, &ok);
    if (!ok) {
      char text[1024] = {};
      gl_.GetShaderInfoLog(shaders[i], sizeof(text), nullptr, text);
      log += text;
    }
    gl_.AttachShader(program, shaders[i]);
  }
  gl_.LinkProgram(program);
  GLint linked = 0;
  gl_.GetProgramiv(program, GL_LINK_STATUS, &linked);
  for (GLuint s : shaders) gl_.DeleteShader(s);
  if (!linked || !log.empty()) {
    char text[1024] = {};
    gl_.GetProgramInfoLog(program, sizeof(text), nullptr, text);
    gl_.DeleteProgram(program);
    return absl::InternalError(core::StrCat("shader build failed: ", log, text));
  }
  return program;
}

absl::Status EglRenderer::InitPrograms() {
  auto surface = Compile(kSurfaceVertex, kSurfaceFragment);
  if (!surface.ok()) return surface.status();
  surface_program_ = *surface;
  auto overlay = Compile(kOverlayVertex, kOverlayFragment);
  if (!overlay.ok()) return overlay.status();
  overlay_program_ = *overlay;
  auto volume = Compile(kVolumeVertex, kVolumeFragment);
  if (!volume.ok()) return volume.status();
  volume_program_ = *volume;
  std::vector<float> table(3 * kColorMapTexels);
  for (int i = 0; i < kColorMapTexels; ++i) {
    const auto rgb = ColorMap(static_cast<double>(i) / (kColorMapTexels - 1));
    std::copy(rgb.begin(), rgb.end(), table.begin() + 3 * i);
  }
  gl_.GenTextures(1, &colormap_);
  gl_.BindTexture(GL_TEXTURE_2D, colormap_);
  gl_.TexImage2D(GL_TEXTURE_2D, 0, GL_RGB32F, kColorMapTexels, 1, 0, GL_RGB, GL_FLOAT, table.data());
  gl_.TexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
  gl_.TexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
  gl_.TexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
  gl_.TexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);
  if (gl_.GetError() != GL_NO_ERROR) return absl::InternalError("GL error while setting up the renderer");
  return absl::OkStatus();
}

void EglRenderer::Shutdown() {
  if (display_ == EGL_NO_DISPLAY) return;
  if (surface_program_) gl_.DeleteProgram(surface_program_);
  if (overlay_program_) gl_.DeleteProgram(overlay_program_);
  if (volume_program_) gl_.DeleteProgram(volume_program_);
  if (colormap_) gl_.DeleteTextures(1, &colormap_);
  eglMakeCurrent(display_, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
  eglDestroyContext(display_, context_);
  eglTerminate(display_);
  display_ = EGL_NO_DISPLAY;
  eglReleaseThread();  // EGL keeps per-thread state until it is released.
}

}  // namespace internal

absl::StatusOr<std::unique_ptr<Renderer>> CreateRenderer(std::string_view backend) {
  if (backend != "egl" && backend != "auto") {
    return absl::InvalidArgumentError(core::StrCat("unknown renderer backend '", backend, "' (available: egl, auto)"));
  }
  return internal::EglRenderer::Create();
}

}  // namespace lsqsurf::render
