// worker/render/gl_api.h — the OpenGL 4.5 core entry points the renderer uses, loaded through
// eglGetProcAddress (internal to worker/render). Loading by hand keeps the program linked to
// libEGL only, which GLVND then dispatches to Mesa or to the NVIDIA driver.
#pragma once

#include <GL/glcorearb.h>

#include <string>

namespace lsqsurf::render::internal {

// A table laid out by hand:
// clang-format off
#define LSQSURF_GL_FUNCTIONS(X)                                                          \
  X(ActiveTexture, ACTIVETEXTURE) X(AttachShader, ATTACHSHADER) X(BindBuffer, BINDBUFFER) \
  X(BindFramebuffer, BINDFRAMEBUFFER) X(BindRenderbuffer, BINDRENDERBUFFER)              \
  X(BindTexture, BINDTEXTURE) X(BindVertexArray, BINDVERTEXARRAY)                         \
  X(BlitFramebuffer, BLITFRAMEBUFFER) X(BufferData, BUFFERDATA)                           \
  X(CheckFramebufferStatus, CHECKFRAMEBUFFERSTATUS) X(Clear, CLEAR)                       \
  X(ClearColor, CLEARCOLOR) X(CompileShader, COMPILESHADER) X(CreateProgram, CREATEPROGRAM) \
  X(CreateShader, CREATESHADER) X(DeleteBuffers, DELETEBUFFERS)                           \
  X(DeleteFramebuffers, DELETEFRAMEBUFFERS) X(DeleteProgram, DELETEPROGRAM)               \
  X(DeleteRenderbuffers, DELETERENDERBUFFERS) X(DeleteShader, DELETESHADER)               \
  X(DeleteTextures, DELETETEXTURES) X(DeleteVertexArrays, DELETEVERTEXARRAYS)             \
  X(Disable, DISABLE) X(DisableVertexAttribArray, DISABLEVERTEXATTRIBARRAY)               \
  X(DrawArrays, DRAWARRAYS) X(DrawElements, DRAWELEMENTS) X(Enable, ENABLE)               \
  X(EnableVertexAttribArray, ENABLEVERTEXATTRIBARRAY) X(Finish, FINISH)                   \
  X(FramebufferRenderbuffer, FRAMEBUFFERRENDERBUFFER) X(GenBuffers, GENBUFFERS)           \
  X(GenFramebuffers, GENFRAMEBUFFERS) X(GenRenderbuffers, GENRENDERBUFFERS)               \
  X(GenTextures, GENTEXTURES) X(GenVertexArrays, GENVERTEXARRAYS) X(GetError, GETERROR)   \
  X(GetIntegerv, GETINTEGERV) X(GetRenderbufferParameteriv, GETRENDERBUFFERPARAMETERIV)     \
  X(GetProgramInfoLog, GETPROGRAMINFOLOG) X(GetProgramiv, GETPROGRAMIV)                   \
  X(GetShaderInfoLog, GETSHADERINFOLOG) X(GetShaderiv, GETSHADERIV) X(GetString, GETSTRING) \
  X(GetUniformLocation, GETUNIFORMLOCATION) X(LinkProgram, LINKPROGRAM)                   \
  X(PixelStorei, PIXELSTOREI) X(PolygonMode, POLYGONMODE) X(PolygonOffset, POLYGONOFFSET) \
  X(ReadPixels, READPIXELS) X(RenderbufferStorageMultisample, RENDERBUFFERSTORAGEMULTISAMPLE) \
  X(ShaderSource, SHADERSOURCE) X(TexImage2D, TEXIMAGE2D) X(TexParameteri, TEXPARAMETERI) \
  X(Uniform1f, UNIFORM1F) X(Uniform1i, UNIFORM1I) X(Uniform2f, UNIFORM2F)                 \
  X(Uniform3f, UNIFORM3F) X(UniformMatrix4fv, UNIFORMMATRIX4FV) X(UseProgram, USEPROGRAM) \
  X(VertexAttrib1f, VERTEXATTRIB1F) X(VertexAttribPointer, VERTEXATTRIBPOINTER)           \
  X(Viewport, VIEWPORT) X(DepthFunc, DEPTHFUNC) X(BlendFunc, BLENDFUNC)          \
  X(CullFace, CULLFACE) X(FrontFace, FRONTFACE) X(TexImage3D, TEXIMAGE3D) X(Uniform1fv, UNIFORM1FV)
// clang-format on

struct GlApi {
#define LSQSURF_GL_MEMBER(name, upper) PFNGL##upper##PROC name = nullptr;
  LSQSURF_GL_FUNCTIONS(LSQSURF_GL_MEMBER)
#undef LSQSURF_GL_MEMBER

  // Loads every entry point; returns the name of the first missing one, or "" when all loaded.
  std::string Load();
};

}  // namespace lsqsurf::render::internal
