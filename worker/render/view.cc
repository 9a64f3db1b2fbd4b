#include "worker/render/view.h"

#include <algorithm>
#include <cmath>
#include <numbers>

namespace lsqsurf::render::internal {

View MakeView(const core::Box3& model_box, const RenderParams& p) {
  const core::Box3& box = p.camera.framing_box.isEmpty() ? model_box : p.camera.framing_box;
  const Eigen::Vector3d lo = box.min(), hi = box.max();
  const Eigen::Vector3d centre = 0.5 * (lo + hi);
  const double radius = std::max(0.5 * (hi - lo).norm(), 1e-9);
  const double aspect = static_cast<double>(p.width) / p.height;
  const double half_fov = 0.5 * p.camera.fov_deg * std::numbers::pi / 180;
  // The narrower of the two half-angles must hold the bounding sphere.
  const double half_narrow = aspect < 1 ? std::atan(std::tan(half_fov) * aspect) : half_fov;
  View view;
  view.distance = p.camera.distance > 0 ? p.camera.distance : 1.02 * radius / std::sin(half_narrow);
  const double az = p.camera.azimuth_deg * std::numbers::pi / 180, el = p.camera.elevation_deg * std::numbers::pi / 180;
  // The up axis and the two after it in cyclic order (x → y → z → x).
  const int k = p.camera.up == UpAxis::kX ? 0 : p.camera.up == UpAxis::kY ? 1 : 2;
  const Eigen::Vector3d up_axis = Eigen::Vector3d::Unit(k);
  const Eigen::Vector3d first = Eigen::Vector3d::Unit((k + 1) % 3), second = Eigen::Vector3d::Unit((k + 2) % 3);
  const Eigen::Vector3d back = std::cos(el) * (std::cos(az) * first + std::sin(az) * second) + std::sin(el) * up_axis;
  const Eigen::Vector3d eye = centre + view.distance * back;
  view.eye = eye;
  const Eigen::Vector3d right = up_axis.cross(back).normalized();
  const Eigen::Vector3d up = back.cross(right);
  Eigen::Matrix4d mv = Eigen::Matrix4d::Identity();
  mv.block<1, 3>(0, 0) = right.transpose();
  mv.block<1, 3>(1, 0) = up.transpose();
  mv.block<1, 3>(2, 0) = back.transpose();
  mv.block<3, 1>(0, 3) = -mv.block<3, 3>(0, 0) * eye;
  const double near = std::max(view.distance - 1.05 * radius, 1e-4 * view.distance);
  const double far = view.distance + 1.05 * radius;
  const double f = 1.0 / std::tan(half_fov);
  Eigen::Matrix4d proj = Eigen::Matrix4d::Zero();
  proj(0, 0) = f / aspect;
  proj(1, 1) = f;
  proj(2, 2) = (far + near) / (near - far);
  proj(2, 3) = 2 * far * near / (near - far);
  proj(3, 2) = -1;
  view.model_view = mv.cast<float>();
  view.projection = proj.cast<float>();
  return view;
}

}  // namespace lsqsurf::render::internal
