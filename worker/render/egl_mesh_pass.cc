// The EGL renderer's mesh and point pass: render targets, attributes, shading, the legend.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <numbers>

#include "stb_easy_font.h"
#include "worker/core/strings.h"
#include "worker/render/egl_renderer.h"

namespace lsqsurf::render::internal {

using core::Vec3f;
using Matrix4 = Eigen::Matrix4f;

absl::StatusOr<EglRenderer::Targets> EglRenderer::MakeTargets(int w, int h, int samples) {
  Targets t;
  const int asked = std::min(samples, max_samples_);
  const GLsizei storage = asked <= 1 ? 0 : asked;
  gl_.GenFramebuffers(2, t.fbo);
  gl_.GenRenderbuffers(3, t.rbo);
  gl_.BindRenderbuffer(GL_RENDERBUFFER, t.rbo[0]);
  gl_.RenderbufferStorageMultisample(GL_RENDERBUFFER, storage, GL_RGBA8, w, h);
  GLint granted = 0;
  gl_.GetRenderbufferParameteriv(GL_RENDERBUFFER, GL_RENDERBUFFER_SAMPLES, &granted);
  t.samples = std::max(1, granted);
  gl_.BindRenderbuffer(GL_RENDERBUFFER, t.rbo[1]);
  gl_.RenderbufferStorageMultisample(GL_RENDERBUFFER, storage, GL_DEPTH_COMPONENT24, w, h);
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
        core::StrCat("the GL could not allocate a ", w, "x", h, " image with ", asked, " samples"));
  }
  return t;
}

void EglRenderer::ReleaseTargets(Targets& t) {
  gl_.BindFramebuffer(GL_FRAMEBUFFER, 0);
  gl_.DeleteFramebuffers(2, t.fbo);
  gl_.DeleteRenderbuffers(3, t.rbo);
}

void EglRenderer::UploadAttributes(const Drawable& d, const GLuint* buffers, bool has_normals, bool colour) {
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

void EglRenderer::SetUniforms(const RenderParams& p, const View& view, double lo, double span, bool has_normals,
                              bool colour) {
  const GLuint prog = surface_program_;
  gl_.UseProgram(prog);
  auto uniform = [&](const char* name) { return gl_.GetUniformLocation(prog, name); };
  gl_.UniformMatrix4fv(uniform("model_view"), 1, GL_FALSE, view.model_view.data());
  gl_.UniformMatrix4fv(uniform("projection"), 1, GL_FALSE, view.projection.data());
  gl_.Uniform2f(uniform("scalar_map"), static_cast<float>(lo), static_cast<float>(1.0 / span));
  gl_.Uniform1i(uniform("flat_shading"), p.shading == Shading::kFlat ? 1 : 0);
  gl_.Uniform1i(uniform("has_normals"), has_normals ? 1 : 0);
  gl_.Uniform1i(uniform("use_colormap"), colour ? 1 : 0);
  gl_.Uniform1i(uniform("packed_rgb"), colour && p.color_attribute == kTrueColour ? 1 : 0);
  gl_.Uniform3f(uniform("base_color"), p.base_color[0], p.base_color[1], p.base_color[2]);
  const Eigen::Vector3f light = Eigen::Vector3f(-std::tan(0.4363f), std::tan(0.4363f), 1.0f).normalized();  // 25°.
  gl_.Uniform3f(uniform("light_dir"), light.x(), light.y(), light.z());
  gl_.Uniform1f(uniform("specular"), static_cast<float>(p.specular));
  gl_.ActiveTexture(GL_TEXTURE0);
  gl_.BindTexture(GL_TEXTURE_2D, colormap_);
  gl_.Uniform1i(uniform("colormap"), 0);
}

void EglRenderer::DrawFaces(const Drawable& d, const RenderParams& p, const View& view, GLuint index_buffer) {
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

void EglRenderer::DrawPoints(const Drawable& d, const RenderParams& p, const View& view) {
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

Image EglRenderer::ReadBack(const Targets& t, int w, int h, GLenum* error) {
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

absl::StatusOr<EglRenderer::Picture> EglRenderer::BeginPicture(const core::Box3& box, const RenderParams& p, double lo,
                                                               double hi) {
  Picture picture;
  auto targets = MakeTargets(p.width, p.height, p.samples);
  if (!targets.ok()) return targets.status();
  picture.targets = *targets;
  gl_.BindFramebuffer(GL_FRAMEBUFFER, picture.targets.fbo[0]);
  gl_.Viewport(0, 0, p.width, p.height);
  gl_.ClearColor(p.background[0], p.background[1], p.background[2], p.transparent ? 0.0f : 1.0f);
  gl_.Clear(GL_COLOR_BUFFER_BIT | GL_DEPTH_BUFFER_BIT);
  gl_.Enable(GL_DEPTH_TEST);
  gl_.DepthFunc(GL_LESS);
  if (picture.targets.samples > 1) gl_.Enable(GL_MULTISAMPLE);
  picture.view = MakeView(box, p);
  picture.lo = lo;
  picture.hi = hi;
  return picture;
}

void EglRenderer::DrawInto(const Drawable& d, const RenderParams& p, const Picture& picture) {
  GLuint vao = 0, buffers[4] = {};
  gl_.GenVertexArrays(1, &vao);
  gl_.BindVertexArray(vao);
  gl_.GenBuffers(4, buffers);
  const bool has_normals = d.normals.size() == d.positions.size();
  const bool colour = !d.scalars.empty() && d.scalars.size() == d.positions.size();
  UploadAttributes(d, buffers, has_normals, colour);
  const double span = picture.hi > picture.lo ? picture.hi - picture.lo : 1.0;
  SetUniforms(p, picture.view, picture.lo, span, has_normals, colour);
  if (!d.faces.empty()) {
    DrawFaces(d, p, picture.view, buffers[3]);
  } else {
    DrawPoints(d, p, picture.view);
  }
  gl_.BindVertexArray(0);
  gl_.DeleteBuffers(4, buffers);
  gl_.DeleteVertexArrays(1, &vao);
}

absl::StatusOr<Image> EglRenderer::FinishPicture(Picture& picture, const RenderParams& p, RenderInfo* info) {
  if (picture.coloured && p.legend && p.color_attribute != kTrueColour) {
    DrawLegend(p.width, p.height, picture.lo, picture.hi);
  }
  GLenum error = GL_NO_ERROR;
  Image image = ReadBack(picture.targets, p.width, p.height, &error);
  ReleaseTargets(picture.targets);
  gl_.Disable(GL_DEPTH_TEST);
  if (error == GL_OUT_OF_MEMORY) return absl::ResourceExhaustedError("the GL ran out of memory drawing the image");
  if (error != GL_NO_ERROR)
    return absl::InternalError(core::StrCat("GL error 0x", std::to_string(error), " while drawing"));
  if (info) {
    info->color_min = picture.lo;
    info->color_max = picture.hi;
    info->renderer = renderer_;
    info->samples = picture.targets.samples;
  }
  return image;
}

absl::StatusOr<Image> EglRenderer::Draw(const Drawable& d, const RenderParams& p, RenderInfo* info) {
  // Colour range: the request's, or the data's.
  double lo = p.color_min, hi = p.color_max;
  if (!d.scalars.empty() && lo == hi) {
    const auto [mn, mx] = std::minmax_element(d.scalars.begin(), d.scalars.end());
    lo = *mn;
    hi = *mx;
  }
  auto picture = BeginPicture(d.box, p, lo, hi);
  if (!picture.ok()) return picture.status();
  picture->coloured = !d.scalars.empty() && d.scalars.size() == d.positions.size();
  DrawInto(d, p, *picture);
  return FinishPicture(*picture, p, info);
}

void EglRenderer::DrawLegend(int w, int h, double lo, double hi) {
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

}  // namespace lsqsurf::render::internal
