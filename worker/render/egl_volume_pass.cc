// The EGL renderer's volume pass: the grid as a 3-D texture, ray-cast in a fragment shader.
#include <Eigen/Geometry>

#include "worker/core/strings.h"
#include "worker/render/egl_renderer.h"
#include "worker/render/egl_shaders.h"

namespace lsqsurf::render::internal {

absl::StatusOr<Image> EglRenderer::DrawVolume(const VolumeGrid& g, const std::vector<float>& texels,
                                              const std::vector<std::array<double, 2>>& opacity,
                                              std::pair<double, double> range, const RenderParams& p,
                                              RenderInfo* info) {
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

void EglRenderer::SetVolumeUniforms(const VolumeGrid& g, const core::Box3& box,
                                    const std::vector<std::array<double, 2>>& opacity, std::pair<double, double> range,
                                    const RenderParams& p) {
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

}  // namespace lsqsurf::render::internal
