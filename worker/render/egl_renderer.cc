// The EGL backend of worker/render: one OpenGL 4.5 core context, owned by a render thread.
#include <EGL/egl.h>
#include <EGL/eglext.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <functional>
#include <future>
#include <mutex>
#include <numbers>
#include <thread>

#if defined(__SANITIZE_ADDRESS__)
#include <sanitizer/lsan_interface.h>
#endif

#include "stb_easy_font.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/render/face_culling.h"
#include "worker/render/gl_api.h"
#include "worker/render/render.h"
#include "worker/render/view.h"

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

}  // namespace internal

namespace {

using internal::MakeView;
using internal::View;

using core::Vec3f;
using Matrix4 = Eigen::Matrix4f;

constexpr char kSurfaceVertex[] = R"(#version 450 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in float scalar;
uniform mat4 model_view;
uniform mat4 projection;
uniform vec2 scalar_map;   // (min, 1 / (max - min))
uniform float point_size;
out vec3 view_position;
out vec3 view_normal;
out float color_t;
void main() {
  vec4 p = model_view * vec4(position, 1.0);
  view_position = p.xyz;
  view_normal = mat3(model_view) * normal;
  color_t = (scalar - scalar_map.x) * scalar_map.y;
  gl_PointSize = point_size;
  gl_Position = projection * p;
}
)";

// mode 0: shaded surface; 1: wireframe lines; 2: point splats (round, shaded by their normal,
// or as small spheres when the cloud has none).
constexpr char kSurfaceFragment[] = R"(#version 450 core
in vec3 view_position;
in vec3 view_normal;
in float color_t;
uniform int mode;
uniform int flat_shading;
uniform int has_normals;
uniform int use_colormap;
uniform vec3 base_color;
uniform vec3 light_dir;
uniform float specular;
uniform sampler2D colormap;
out vec4 fragment;
void main() {
  if (mode == 1) { fragment = vec4(0.08, 0.08, 0.10, 1.0); return; }
  vec3 n;
  if (mode == 2) {
    vec2 c = 2.0 * gl_PointCoord - 1.0;
    float r2 = dot(c, c);
    if (r2 > 1.0) discard;
    n = has_normals != 0 ? normalize(view_normal) : vec3(c.x, -c.y, sqrt(1.0 - r2));
  } else if (flat_shading != 0 || has_normals == 0) {
    n = normalize(cross(dFdx(view_position), dFdy(view_position)));
  } else {
    n = normalize(view_normal);
  }
  vec3 v = normalize(-view_position);
  if (dot(n, v) < 0.0) n = -n;  // Two-sided: open surfaces show their back faces lit too.
  vec3 albedo = use_colormap != 0 ? texture(colormap, vec2(clamp(color_t, 0.0, 1.0), 0.5)).rgb : base_color;
  float diffuse = max(dot(n, light_dir), 0.0);
  float highlight = specular * pow(max(dot(n, normalize(light_dir + v)), 0.0), 48.0);
  fragment = vec4(albedo * (0.18 + 0.82 * diffuse) + vec3(highlight), 1.0);
}
)";

// Screen-space overlay (legend bar and labels): positions in pixels, t < 0 = label colour.
constexpr char kOverlayVertex[] = R"(#version 450 core
layout(location = 0) in vec2 pixel;
layout(location = 2) in float t;
uniform vec2 viewport;
out float color_t;
void main() {
  color_t = t;
  gl_Position = vec4(2.0 * pixel.x / viewport.x - 1.0, 1.0 - 2.0 * pixel.y / viewport.y, 0.0, 1.0);
}
)";

constexpr char kOverlayFragment[] = R"(#version 450 core
in float color_t;
uniform sampler2D colormap;
out vec4 fragment;
void main() {
  fragment = color_t < 0.0 ? vec4(0.05, 0.05, 0.05, 1.0) : vec4(texture(colormap, vec2(color_t, 0.5)).rgb, 1.0);
}
)";

constexpr int kColorMapTexels = 256;
constexpr int kMaxOpacityPoints = 16;

// Volume ray casting: one full-screen triangle; each fragment marches its ray through a 3-D
// texture of (value, gradient) exactly as RaycastVolume does on the CPU (render.h).
constexpr char kVolumeVertex[] = R"(#version 450 core
void main() {
  vec2 corner = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);
}
)";

constexpr char kVolumeFragment[] = R"(#version 450 core
uniform sampler3D field;
uniform sampler2D colormap;
uniform mat4 inverse_view_projection;
uniform vec2 viewport;
uniform vec3 box_min, box_max, dims;
uniform float step, step_cells, lo, span, iso, specular, back_alpha;
uniform int mode, opacity_count;
uniform float opacity_t[16], opacity_a[16];
uniform vec3 background, base_color;
out vec4 fragment;

vec4 at(vec3 x) {
  vec3 t = (x - box_min) / (box_max - box_min);
  if (any(lessThan(t, vec3(0.0))) || any(greaterThan(t, vec3(1.0)))) return vec4(0.0 / 0.0);
  return texture(field, (t * (dims - 1.0) + 0.5) / dims);
}
float opacity(float t) {
  if (t <= opacity_t[0]) return opacity_a[0];
  for (int k = 1; k < opacity_count; ++k) {
    if (t <= opacity_t[k]) {
      float u = (t - opacity_t[k - 1]) / max(opacity_t[k] - opacity_t[k - 1], 1e-12);
      return mix(opacity_a[k - 1], opacity_a[k], u);
    }
  }
  return opacity_a[opacity_count - 1];
}
float diffuse(vec3 g, vec3 dir) { float n = length(g); return n > 0.0 ? abs(dot(g, dir)) / n : 1.0; }
bool finite(float v) { return !isnan(v) && !isinf(v); }

void main() {
  vec2 ndc = gl_FragCoord.xy / viewport * 2.0 - 1.0;
  vec4 a = inverse_view_projection * vec4(ndc, -1.0, 1.0), b = inverse_view_projection * vec4(ndc, 1.0, 1.0);
  vec3 from = a.xyz / a.w, dir = normalize(b.xyz / b.w - from);
  vec3 u0 = (box_min - from) / dir, u1 = (box_max - from) / dir;
  vec3 near = min(u0, u1), far = max(u0, u1);
  float t0 = max(max(max(near.x, near.y), near.z), 0.0), t1 = min(min(far.x, far.y), far.z);
  vec3 color = vec3(0.0);
  float alpha = 0.0;
  vec4 previous = vec4(0.0 / 0.0);
  for (float t = t0; t <= t1 && alpha < 0.995; t += step) {
    vec4 s = at(from + t * dir);
    if (mode == 1) {
      if (finite(s.x) && finite(previous.x) && ((s.x >= iso) != (previous.x >= iso))) {
        float ta = t - step, tb = t, fa = previous.x - iso;
        vec4 hit = s;
        for (int it = 0; it < 8; ++it) {
          float tm = 0.5 * (ta + tb);
          vec4 m = at(from + tm * dir);
          if (!finite(m.x)) break;
          hit = m;
          if ((m.x - iso < 0.0) == (fa < 0.0)) { ta = tm; fa = m.x - iso; } else { tb = tm; }
        }
        float d = diffuse(hit.yzw, dir);
        color = base_color * (0.18 + 0.82 * d) + vec3(specular * pow(d, 48.0));
        alpha = 1.0;
        break;
      }
      previous = s;
      continue;
    }
    if (!finite(s.x)) continue;
    float u = clamp((s.x - lo) / span, 0.0, 1.0);
    float a_cell = opacity(u);
    if (a_cell <= 0.0) continue;
    float a_step = 1.0 - pow(1.0 - min(a_cell, 0.999999), step_cells);
    vec3 c = texture(colormap, vec2(u * (255.0 / 256.0) + 0.5 / 256.0, 0.5)).rgb;
    float light = 0.35 + 0.65 * diffuse(s.yzw, dir);
    color += (1.0 - alpha) * a_step * light * c;
    alpha += (1.0 - alpha) * a_step;
  }
  fragment = vec4(color + (1.0 - alpha) * back_alpha * background, back_alpha > 0.0 ? 1.0 : alpha);
}
)";

// Geometry handed to the GL: positions, optional normals and scalars, optional triangles, and
// what the caller's thread worked out about them (the render thread only draws).
struct Drawable {
  std::span<const Vec3f> positions, normals;
  std::span<const float> scalars;
  std::span<const core::Triangle> faces;  // Empty: points.
  core::Box3 box{};
  OutsideWinding winding = OutsideWinding::kUnknown;
};

class EglRenderer final : public Renderer {
 public:
  static absl::StatusOr<std::unique_ptr<Renderer>> Create() {
    std::unique_ptr<EglRenderer> r(new EglRenderer());
    std::promise<absl::Status> ready;
    auto started = ready.get_future();
    r->thread_ = std::thread([raw = r.get(), &ready] { raw->Loop(ready); });
    if (absl::Status s = started.get(); !s.ok()) return s;
    return std::unique_ptr<Renderer>(std::move(r));
  }

  ~EglRenderer() override {
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
    }
    wake_.notify_all();
    if (thread_.joinable()) thread_.join();
  }

  absl::StatusOr<Image> RenderMesh(const core::TriangleMesh& mesh, const RenderParams& params,
                                   RenderInfo* info) override {
    LSQSURF_RETURN_IF_ERROR(Validate(params));
    if (mesh.faces.empty()) return absl::InvalidArgumentError("the mesh has no triangles to draw");
    auto scalars = FindScalars(mesh.vertex_attributes, params.color_attribute);
    if (!scalars.ok()) return scalars.status();
    return Enqueue({mesh.vertices, mesh.normals, *scalars, mesh.faces}, params, info);
  }

  absl::StatusOr<Image> RenderPoints(const core::PointCloud& cloud, const RenderParams& params,
                                     RenderInfo* info) override {
    LSQSURF_RETURN_IF_ERROR(Validate(params));
    if (cloud.positions.empty()) return absl::InvalidArgumentError("the point cloud is empty");
    auto scalars = FindScalars(cloud.attributes, params.color_attribute);
    if (!scalars.ok()) return scalars.status();
    return Enqueue({cloud.positions, cloud.normals, *scalars, {}}, params, info);
  }

  absl::StatusOr<Image> RenderVolume(const VolumeGrid& grid, const RenderParams& params, RenderInfo* info) override {
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

  std::string description() const override { return description_; }

 private:
  EglRenderer() = default;

  static absl::StatusOr<std::span<const float>> FindScalars(const std::vector<core::ScalarAttribute>& attributes,
                                                            const std::string& name) {
    if (name.empty()) return std::span<const float>();
    std::string known;
    for (const core::ScalarAttribute& a : attributes) {
      if (a.name == name) return std::span<const float>(a.values);
      known += (known.empty() ? "" : ", ") + a.name;
    }
    return absl::InvalidArgumentError(
        core::StrCat("no attribute '", name, "' to colour by; this result has: ", known.empty() ? "none" : known));
  }

  // Measures the geometry on the calling thread, then draws it on the render thread.
  absl::StatusOr<Image> Enqueue(Drawable d, const RenderParams& params, RenderInfo* info) {
    d.box = core::BoundingBox(d.positions);
    if (!d.faces.empty()) d.winding = ClosedMeshOutsideWinding(d.positions, d.normals, d.faces);
    return Run([&] { return Draw(d, params, info); });
  }

  // Runs `work` on the render thread and waits for it.
  absl::StatusOr<Image> Run(std::function<absl::StatusOr<Image>()> work) {
    std::packaged_task<absl::StatusOr<Image>()> task(std::move(work));
    auto result = task.get_future();
    {
      std::lock_guard lock(mutex_);
      tasks_.push_back(std::move(task));
    }
    wake_.notify_one();
    return result.get();
  }

  void Loop(std::promise<absl::Status>& ready) {
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

  // The EGL device platform first (NVIDIA's headless path; Mesa exposes its software device
  // the same way), then Mesa's surfaceless platform.
  absl::Status InitContext() {
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
    return absl::UnavailableError(core::StrCat(
        "no OpenGL 4.5 context through EGL (tried: ", tried.empty() ? "no EGL devices or platforms" : tried,
        "); install Mesa (libegl-mesa0, libgl1-mesa-dri) or a GPU driver"));
  }

  bool TryDisplay(EGLDisplay display, const std::string& what, std::string& tried) {
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
    description_ = core::StrCat("egl (", what, "): ", renderer_);
    return true;
  }

  absl::StatusOr<GLuint> Compile(const char* vertex, const char* fragment) {
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

  absl::Status InitPrograms() {
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

  void Shutdown() {
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

  // Multisampled colour + depth, resolved into a single-sample colour buffer.
  struct Targets {
    GLuint fbo[2] = {}, rbo[3] = {};
  };
  absl::StatusOr<Targets> MakeTargets(int w, int h, int samples) {
    Targets t;
    gl_.GenFramebuffers(2, t.fbo);
    gl_.GenRenderbuffers(3, t.rbo);
    gl_.BindRenderbuffer(GL_RENDERBUFFER, t.rbo[0]);
    gl_.RenderbufferStorageMultisample(GL_RENDERBUFFER, samples, GL_RGBA8, w, h);
    gl_.BindRenderbuffer(GL_RENDERBUFFER, t.rbo[1]);
    gl_.RenderbufferStorageMultisample(GL_RENDERBUFFER, samples, GL_DEPTH_COMPONENT24, w, h);
    gl_.BindRenderbuffer(GL_RENDERBUFFER, t.rbo[2]);
    gl_.RenderbufferStorageMultisample(GL_RENDERBUFFER, 0, GL_RGBA8, w, h);
    gl_.BindFramebuffer(GL_FRAMEBUFFER, t.fbo[0]);
    gl_.FramebufferRenderbuffer(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_RENDERBUFFER, t.rbo[0]);
    gl_.FramebufferRenderbuffer(GL_FRAMEBUFFER, GL_DEPTH_ATTACHMENT, GL_RENDERBUFFER, t.rbo[1]);
    const bool complete = gl_.CheckFramebufferStatus(GL_FRAMEBUFFER) == GL_FRAMEBUFFER_COMPLETE;
    gl_.BindFramebuffer(GL_FRAMEBUFFER, t.fbo[1]);
    gl_.FramebufferRenderbuffer(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_RENDERBUFFER, t.rbo[2]);
    const bool resolved = gl_.CheckFramebufferStatus(GL_FRAMEBUFFER) == GL_FRAMEBUFFER_COMPLETE;
    if (!complete || !resolved) {
      ReleaseTargets(t);
      gl_.GetError();
      return absl::ResourceExhaustedError(
          core::StrCat("the GL could not allocate a ", w, "x", h, " image with ", samples, " samples"));
    }
    return t;
  }
  void ReleaseTargets(Targets& t) {
    gl_.BindFramebuffer(GL_FRAMEBUFFER, 0);
    gl_.DeleteFramebuffers(2, t.fbo);
    gl_.DeleteRenderbuffers(3, t.rbo);
  }

  // Uploads the vertex attributes into `buffers` (positions, normals, scalars) of the bound VAO.
  void UploadAttributes(const Drawable& d, const GLuint* buffers, bool has_normals, bool colour) {
    auto attribute = [&](GLuint index, GLuint buffer, const void* data, size_t bytes, GLint components) {
      gl_.BindBuffer(GL_ARRAY_BUFFER, buffer);
      gl_.BufferData(GL_ARRAY_BUFFER, static_cast<GLsizeiptr>(bytes), data, GL_STATIC_DRAW);
      gl_.VertexAttribPointer(index, components, GL_FLOAT, GL_FALSE, 0, nullptr);
      gl_.EnableVertexAttribArray(index);
    };
    attribute(0, buffers[0], d.positions.data(), d.positions.size_bytes(), 3);
    if (has_normals) attribute(1, buffers[1], d.normals.data(), d.normals.size_bytes(), 3);
    if (colour) {
      attribute(2, buffers[2], d.scalars.data(), d.scalars.size_bytes(), 1);
    } else {
      gl_.DisableVertexAttribArray(2);
      gl_.VertexAttrib1f(2, 0.0f);
    }
  }

  // The surface program with the view, shading and colour map of this picture.
  void SetUniforms(const RenderParams& p, const View& view, double lo, double span, bool has_normals, bool colour) {
    const GLuint prog = surface_program_;
    gl_.UseProgram(prog);
    auto uniform = [&](const char* name) { return gl_.GetUniformLocation(prog, name); };
    gl_.UniformMatrix4fv(uniform("model_view"), 1, GL_FALSE, view.model_view.data());
    gl_.UniformMatrix4fv(uniform("projection"), 1, GL_FALSE, view.projection.data());
    gl_.Uniform2f(uniform("scalar_map"), static_cast<float>(lo), static_cast<float>(1.0 / span));
    gl_.Uniform1i(uniform("flat_shading"), p.shading == Shading::kFlat ? 1 : 0);
    gl_.Uniform1i(uniform("has_normals"), has_normals ? 1 : 0);
    gl_.Uniform1i(uniform("use_colormap"), colour ? 1 : 0);
    gl_.Uniform3f(uniform("base_color"), p.base_color[0], p.base_color[1], p.base_color[2]);
    const Eigen::Vector3f light = Eigen::Vector3f(-std::tan(0.4363f), std::tan(0.4363f), 1.0f).normalized();  // 25°.
    gl_.Uniform3f(uniform("light_dir"), light.x(), light.y(), light.z());
    gl_.Uniform1f(uniform("specular"), static_cast<float>(p.specular));
    gl_.ActiveTexture(GL_TEXTURE0);
    gl_.BindTexture(GL_TEXTURE_2D, colormap_);
    gl_.Uniform1i(uniform("colormap"), 0);
  }

  void DrawFaces(const Drawable& d, const RenderParams& p, const View& view, GLuint index_buffer) {
    const GLint mode = gl_.GetUniformLocation(surface_program_, "mode");
    gl_.BindBuffer(GL_ELEMENT_ARRAY_BUFFER, index_buffer);
    gl_.BufferData(GL_ELEMENT_ARRAY_BUFFER, static_cast<GLsizeiptr>(d.faces.size_bytes()), d.faces.data(),
                   GL_STATIC_DRAW);
    const auto indices = static_cast<GLsizei>(3 * d.faces.size());
    gl_.Uniform1i(mode, 0);
    // Hidden back faces are skipped on closed meshes seen from outside their box.
    const bool eye_outside = !d.box.contains(view.eye);
    if (d.winding != OutsideWinding::kUnknown && eye_outside) {
      gl_.FrontFace(d.winding == OutsideWinding::kCounterClockwise ? GL_CCW : GL_CW);
      gl_.CullFace(GL_BACK);
      gl_.Enable(GL_CULL_FACE);
    }
    if (p.wireframe) {
      gl_.Enable(GL_POLYGON_OFFSET_FILL);  // Faces slightly behind, so that their edges win.
      gl_.PolygonOffset(1.0f, 1.0f);
    }
    gl_.DrawElements(GL_TRIANGLES, indices, GL_UNSIGNED_INT, nullptr);
    if (p.wireframe) {
      gl_.Disable(GL_POLYGON_OFFSET_FILL);
      gl_.PolygonMode(GL_FRONT_AND_BACK, GL_LINE);
      gl_.Uniform1i(mode, 1);
      gl_.DrawElements(GL_TRIANGLES, indices, GL_UNSIGNED_INT, nullptr);
      gl_.PolygonMode(GL_FRONT_AND_BACK, GL_FILL);
    }
    gl_.Disable(GL_CULL_FACE);
  }

  void DrawPoints(const Drawable& d, const RenderParams& p, const View& view) {
    // Splats about as wide as the spacing of points spread over a surface of the box's size.
    double size = p.point_size;
    if (size <= 0) {
      const double diagonal = core::Diagonal(d.box);
      const double spacing = 1.6 * diagonal / std::sqrt(static_cast<double>(d.positions.size()));
      const double half_height = view.distance * std::tan(0.5 * p.camera.fov_deg * std::numbers::pi / 180);
      size = std::clamp(spacing / (2 * half_height) * p.height, 1.5, 16.0);
    }
    gl_.Enable(GL_PROGRAM_POINT_SIZE);
    gl_.Uniform1f(gl_.GetUniformLocation(surface_program_, "point_size"), static_cast<float>(size));
    gl_.Uniform1i(gl_.GetUniformLocation(surface_program_, "mode"), 2);
    gl_.DrawArrays(GL_POINTS, 0, static_cast<GLsizei>(d.positions.size()));
    gl_.Disable(GL_PROGRAM_POINT_SIZE);
  }

  // Resolves the samples and reads the picture back, top row first; the GL's error, if any.
  Image ReadBack(const Targets& t, int w, int h, GLenum* error) {
    gl_.BindFramebuffer(GL_READ_FRAMEBUFFER, t.fbo[0]);
    gl_.BindFramebuffer(GL_DRAW_FRAMEBUFFER, t.fbo[1]);
    gl_.BlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL_COLOR_BUFFER_BIT, GL_NEAREST);
    gl_.BindFramebuffer(GL_READ_FRAMEBUFFER, t.fbo[1]);
    Image image;
    image.width = w;
    image.height = h;
    image.rgba.resize(4 * static_cast<size_t>(w) * static_cast<size_t>(h));
    gl_.PixelStorei(GL_PACK_ALIGNMENT, 1);
    gl_.ReadPixels(0, 0, w, h, GL_RGBA, GL_UNSIGNED_BYTE, image.rgba.data());
    *error = gl_.GetError();
    // The GL's rows run bottom-up; images here run top-down.
    const size_t row = 4 * static_cast<size_t>(w);
    for (int y = 0; y < h / 2; ++y) {
      std::swap_ranges(image.rgba.begin() + static_cast<std::ptrdiff_t>(row * static_cast<size_t>(y)),
                       image.rgba.begin() + static_cast<std::ptrdiff_t>(row * static_cast<size_t>(y + 1)),
                       image.rgba.begin() + static_cast<std::ptrdiff_t>(row * static_cast<size_t>(h - 1 - y)));
    }
    return image;
  }

  // Render-thread only.
  absl::StatusOr<Image> Draw(const Drawable& d, const RenderParams& p, RenderInfo* info) {
    const int w = p.width, h = p.height;
    auto targets = MakeTargets(w, h, p.samples);
    if (!targets.ok()) return targets.status();
    gl_.BindFramebuffer(GL_FRAMEBUFFER, targets->fbo[0]);
    gl_.Viewport(0, 0, w, h);
    gl_.ClearColor(p.background[0], p.background[1], p.background[2], p.transparent ? 0.0f : 1.0f);
    gl_.Clear(GL_COLOR_BUFFER_BIT | GL_DEPTH_BUFFER_BIT);
    gl_.Enable(GL_DEPTH_TEST);
    gl_.DepthFunc(GL_LESS);
    if (p.samples > 1) gl_.Enable(GL_MULTISAMPLE);

    const View view = MakeView(d.box, p);
    // Colour range: the request's, or the data's.
    double lo = p.color_min, hi = p.color_max;
    if (!d.scalars.empty() && lo == hi) {
      const auto [mn, mx] = std::minmax_element(d.scalars.begin(), d.scalars.end());
      lo = *mn;
      hi = *mx;
    }
    const double span = hi > lo ? hi - lo : 1.0;

    GLuint vao = 0, buffers[4] = {};
    gl_.GenVertexArrays(1, &vao);
    gl_.BindVertexArray(vao);
    gl_.GenBuffers(4, buffers);
    const bool has_normals = d.normals.size() == d.positions.size();
    const bool colour = d.scalars.size() == d.positions.size();
    UploadAttributes(d, buffers, has_normals, colour);
    SetUniforms(p, view, lo, span, has_normals, colour);
    if (!d.faces.empty()) {
      DrawFaces(d, p, view, buffers[3]);
    } else {
      DrawPoints(d, p, view);
    }
    if (colour && p.legend) DrawLegend(w, h, lo, hi);
    GLenum error = GL_NO_ERROR;
    Image image = ReadBack(*targets, w, h, &error);

    gl_.BindVertexArray(0);
    gl_.DeleteBuffers(4, buffers);
    gl_.DeleteVertexArrays(1, &vao);
    ReleaseTargets(*targets);
    gl_.Disable(GL_DEPTH_TEST);
    if (error == GL_OUT_OF_MEMORY) return absl::ResourceExhaustedError("the GL ran out of memory drawing the image");
    if (error != GL_NO_ERROR)
      return absl::InternalError(core::StrCat("GL error 0x", std::to_string(error), " while drawing"));
    if (info) {
      info->color_min = lo;
      info->color_max = hi;
      info->renderer = renderer_;
    }
    return image;
  }

  // Render-thread only.
  absl::StatusOr<Image> DrawVolume(const VolumeGrid& g, const std::vector<float>& texels,
                                   const std::vector<std::array<double, 2>>& opacity, std::pair<double, double> range,
                                   const RenderParams& p, RenderInfo* info) {
    const int w = p.width, h = p.height;
    auto targets = MakeTargets(w, h, 1);
    if (!targets.ok()) return targets.status();
    GLuint texture = 0, vao = 0;
    gl_.GenTextures(1, &texture);
    gl_.ActiveTexture(GL_TEXTURE1);
    gl_.BindTexture(GL_TEXTURE_3D, texture);
    gl_.TexImage3D(GL_TEXTURE_3D, 0, GL_RGBA32F, g.dims[0], g.dims[1], g.dims[2], 0, GL_RGBA, GL_FLOAT, texels.data());
    for (GLenum wrap : {GL_TEXTURE_WRAP_S, GL_TEXTURE_WRAP_T, GL_TEXTURE_WRAP_R}) {
      gl_.TexParameteri(GL_TEXTURE_3D, wrap, GL_CLAMP_TO_EDGE);
    }
    gl_.TexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
    gl_.TexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
    GLenum error = gl_.GetError();
    Image image;
    if (error == GL_NO_ERROR) {
      gl_.BindFramebuffer(GL_FRAMEBUFFER, targets->fbo[0]);
      gl_.Viewport(0, 0, w, h);
      gl_.Disable(GL_DEPTH_TEST);
      const core::Box3 box(
          g.origin,
          g.origin + (core::Vec3d(g.dims[0], g.dims[1], g.dims[2]) - core::Vec3d::Ones()).cwiseProduct(g.spacing));
      SetVolumeUniforms(g, box, opacity, range, p);
      gl_.GenVertexArrays(1, &vao);
      gl_.BindVertexArray(vao);
      gl_.DrawArrays(GL_TRIANGLES, 0, 3);
      image = ReadBack(*targets, w, h, &error);
      gl_.BindVertexArray(0);
      gl_.DeleteVertexArrays(1, &vao);
      gl_.Enable(GL_DEPTH_TEST);
    }
    gl_.DeleteTextures(1, &texture);
    gl_.ActiveTexture(GL_TEXTURE0);
    ReleaseTargets(*targets);
    if (error == GL_OUT_OF_MEMORY) {
      return absl::ResourceExhaustedError("the volume grid does not fit in the GL's memory; lower the resolution");
    }
    if (error != GL_NO_ERROR) return absl::InternalError(core::StrCat("GL error 0x", std::to_string(error)));
    if (info) {
      info->color_min = range.first;
      info->color_max = range.second;
      info->renderer = renderer_;
    }
    return image;
  }

  void SetVolumeUniforms(const VolumeGrid& g, const core::Box3& box, const std::vector<std::array<double, 2>>& opacity,
                         std::pair<double, double> range, const RenderParams& p) {
    const GLuint prog = volume_program_;
    gl_.UseProgram(prog);
    auto uniform = [&](const char* name) { return gl_.GetUniformLocation(prog, name); };
    const View view = MakeView(box, p);
    const Eigen::Matrix4f inverse = (view.projection * view.model_view).inverse();
    gl_.UniformMatrix4fv(uniform("inverse_view_projection"), 1, GL_FALSE, inverse.data());
    gl_.Uniform2f(uniform("viewport"), static_cast<float>(p.width), static_cast<float>(p.height));
    const Eigen::Vector3f lo = box.min().cast<float>(), hi = box.max().cast<float>();
    gl_.Uniform3f(uniform("box_min"), lo.x(), lo.y(), lo.z());
    gl_.Uniform3f(uniform("box_max"), hi.x(), hi.y(), hi.z());
    gl_.Uniform3f(uniform("dims"), static_cast<float>(g.dims[0]), static_cast<float>(g.dims[1]),
                  static_cast<float>(g.dims[2]));
    gl_.Uniform1f(uniform("step"), static_cast<float>(p.ray_step * g.spacing.minCoeff()));
    gl_.Uniform1f(uniform("step_cells"), static_cast<float>(p.ray_step));
    gl_.Uniform1f(uniform("lo"), static_cast<float>(range.first));
    gl_.Uniform1f(uniform("span"), static_cast<float>(range.second > range.first ? range.second - range.first : 1.0));
    gl_.Uniform1f(uniform("iso"), static_cast<float>(p.iso_value));
    gl_.Uniform1f(uniform("specular"), static_cast<float>(p.specular));
    gl_.Uniform1f(uniform("back_alpha"), p.transparent ? 0.0f : 1.0f);
    gl_.Uniform1i(uniform("mode"), p.volume_mode == VolumeMode::kIsosurface ? 1 : 0);
    std::array<float, kMaxOpacityPoints> t{}, a{};
    for (size_t k = 0; k < opacity.size(); ++k) {
      t[k] = static_cast<float>(opacity[k][0]);
      a[k] = static_cast<float>(opacity[k][1]);
    }
    gl_.Uniform1i(uniform("opacity_count"), static_cast<GLint>(opacity.size()));
    gl_.Uniform1fv(uniform("opacity_t"), kMaxOpacityPoints, t.data());
    gl_.Uniform1fv(uniform("opacity_a"), kMaxOpacityPoints, a.data());
    gl_.Uniform3f(uniform("background"), p.background[0], p.background[1], p.background[2]);
    gl_.Uniform3f(uniform("base_color"), p.base_color[0], p.base_color[1], p.base_color[2]);
    gl_.Uniform1i(uniform("field"), 1);
    gl_.ActiveTexture(GL_TEXTURE0);
    gl_.BindTexture(GL_TEXTURE_2D, colormap_);
    gl_.Uniform1i(uniform("colormap"), 0);
  }

  // A vertical colour bar at the right edge, maximum on top, with its bounds printed beside it.
  void DrawLegend(int w, int h, double lo, double hi) {
    const float x0 = static_cast<float>(w) - std::max(24.0f, 0.035f * static_cast<float>(w)) - 8.0f;
    const float x1 = static_cast<float>(w) - 8.0f;
    const float y0 = 0.15f * static_cast<float>(h), y1 = 0.85f * static_cast<float>(h);
    // x, y, t per vertex; two triangles for the bar.
    std::vector<float> vertices = {x0, y1, 0, x1, y1, 0, x1, y0, 1, x0, y1, 0, x1, y0, 1, x0, y0, 1};
    auto label = [&](double value, float y) {
      char text[32];
      std::snprintf(text, sizeof(text), "%.4g", value);
      char quads[4096];
      const int count = stb_easy_font_print(0, 0, text, nullptr, quads, sizeof(quads));
      const float scale = std::max(1.0f, static_cast<float>(h) / 512.0f);
      const float width = static_cast<float>(stb_easy_font_width(text)) * scale;
      for (int q = 0; q < count; ++q) {
        const auto* v = reinterpret_cast<const float*>(quads + 64 * q);  // 4 vertices × (x, y, z, rgba).
        auto corner = [&](int c) {
          vertices.insert(vertices.end(), {x1 - width + v[4 * c] * scale, y + v[4 * c + 1] * scale, -1.0f});
        };
        for (int c : {0, 1, 2, 0, 2, 3}) corner(c);
      }
    };
    label(hi, y0 - 12.0f * std::max(1.0f, static_cast<float>(h) / 512.0f));
    label(lo, y1 + 4.0f);
    gl_.Disable(GL_DEPTH_TEST);
    gl_.UseProgram(overlay_program_);
    gl_.Uniform2f(gl_.GetUniformLocation(overlay_program_, "viewport"), static_cast<float>(w), static_cast<float>(h));
    gl_.Uniform1i(gl_.GetUniformLocation(overlay_program_, "colormap"), 0);
    GLuint vao = 0, buffer = 0;
    gl_.GenVertexArrays(1, &vao);
    gl_.BindVertexArray(vao);
    gl_.GenBuffers(1, &buffer);
    gl_.BindBuffer(GL_ARRAY_BUFFER, buffer);
    gl_.BufferData(GL_ARRAY_BUFFER, static_cast<GLsizeiptr>(vertices.size() * sizeof(float)), vertices.data(),
                   GL_STREAM_DRAW);
    gl_.VertexAttribPointer(0, 2, GL_FLOAT, GL_FALSE, 3 * sizeof(float), nullptr);
    gl_.EnableVertexAttribArray(0);
    gl_.VertexAttribPointer(2, 1, GL_FLOAT, GL_FALSE, 3 * sizeof(float),
                            reinterpret_cast<const void*>(2 * sizeof(float)));
    gl_.EnableVertexAttribArray(2);
    gl_.DrawArrays(GL_TRIANGLES, 0, static_cast<GLsizei>(vertices.size() / 3));
    gl_.DeleteBuffers(1, &buffer);
    gl_.DeleteVertexArrays(1, &vao);
    gl_.Enable(GL_DEPTH_TEST);
  }

  internal::GlApi gl_;
  EGLDisplay display_ = EGL_NO_DISPLAY;
  EGLContext context_ = EGL_NO_CONTEXT;
  GLuint surface_program_ = 0, overlay_program_ = 0, volume_program_ = 0, colormap_ = 0;
  std::string renderer_, description_;

  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<std::packaged_task<absl::StatusOr<Image>()>> tasks_;
  bool stopping_ = false;
};

}  // namespace

absl::StatusOr<std::unique_ptr<Renderer>> CreateRenderer(std::string_view backend) {
  if (backend != "egl" && backend != "auto") {
    return absl::InvalidArgumentError(core::StrCat("unknown renderer backend '", backend, "' (available: egl, auto)"));
  }
  return EglRenderer::Create();
}

}  // namespace lsqsurf::render
