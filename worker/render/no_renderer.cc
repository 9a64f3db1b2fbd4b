// The renderer of a build without EGL (-DLSQSURF_WITH_EGL=OFF): every picture is refused with
// kUnavailable, which the service reports to callers ("this server cannot draw"), so that the
// rest of the product builds and runs on machines without EGL or OpenGL.
#include "worker/core/strings.h"
#include "worker/render/render.h"

namespace lsqsurf::render {

absl::StatusOr<std::unique_ptr<Renderer>> CreateRenderer(std::string_view backend) {
  if (backend != "egl" && backend != "auto") {
    return absl::InvalidArgumentError(core::StrCat("unknown renderer backend '", backend, "' (available: egl, auto)"));
  }
  return absl::UnavailableError("this build draws no pictures (built with -DLSQSURF_WITH_EGL=OFF)");
}

}  // namespace lsqsurf::render
