// worker/render/view.h — the camera of a picture as matrices (internal to worker/render): one
// definition for the GL backend and the CPU volume ray caster, so that both see the same view.
#pragma once

#include <Eigen/Core>

#include "worker/render/render.h"

namespace lsqsurf::render::internal {

// Matrices of the requested view of a box.
struct View {
  Eigen::Matrix4f model_view, projection;
  double distance = 0;
  Eigen::Vector3d eye;
};

// The view of `model_box` (or of the camera's framing box) that `p` asks for (see render.h).
View MakeView(const core::Box3& model_box, const RenderParams& p);

}  // namespace lsqsurf::render::internal
