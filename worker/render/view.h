// worker/render/view.h — the camera of a picture as matrices, and the colour range of a volume
// picture (internal to worker/render): one definition for the GL backend and the CPU volume ray
// caster, so that both draw the same picture.
#pragma once

#include <Eigen/Core>
#include <utility>

#include "worker/render/render.h"

namespace lsqsurf::render::internal {

// Matrices of the requested view of a box.
struct View {
  Eigen::Matrix4f model_view, projection;
  double distance = 0;
  Eigen::Vector3d eye;
};

// The colour range of a volume picture: the request's, or the finite values' range.
std::pair<double, double> VolumeColorRange(const VolumeGrid& grid, const RenderParams& p);

// The view of `model_box` (or of the camera's framing box) that `p` asks for (see render.h).
View MakeView(const core::Box3& model_box, const RenderParams& p);

}  // namespace lsqsurf::render::internal
