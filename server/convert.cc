#include "server/convert.h"

namespace lsqsurf::server {

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

namespace {

v1::JobState ToProto(jobs::JobState state) {
  switch (state) {
    case jobs::JobState::kQueued: return v1::JOB_STATE_QUEUED;
    case jobs::JobState::kRunning: return v1::JOB_STATE_RUNNING;
    case jobs::JobState::kSucceeded: return v1::JOB_STATE_SUCCEEDED;
    case jobs::JobState::kFailed: return v1::JOB_STATE_FAILED;
    case jobs::JobState::kCancelled: return v1::JOB_STATE_CANCELLED;
  }
  return v1::JOB_STATE_UNSPECIFIED;
}

}  // namespace

void ToProto(const jobs::JobRecord& r, v1::Job* out) {
  out->set_id(r.id);
  out->mutable_spec()->set_method(r.spec.method);
  for (const auto& [name, value] : r.spec.parameters) (*out->mutable_spec()->mutable_parameters())[name] = value;
  out->mutable_spec()->set_mesh_position_bits(r.spec.mesh_position_bits);
  out->set_state(ToProto(r.state));
  out->set_stage(r.stage);
  out->set_progress(r.progress);
  out->set_error(r.error);
  out->set_attempts(r.attempts);
  out->set_created_ms(r.created_ms);
  out->set_updated_ms(r.updated_ms);
  out->set_input_points(r.input_points);
  out->set_input_bytes(r.input_bytes);
  for (const auto& [name, value] : r.statistics) {
    v1::Statistic* s = out->add_statistics();
    s->set_name(name);
    s->set_value(value);
  }
  for (const auto& name : r.results) out->add_results(name);
}

jobs::JobSpec FromProto(const v1::JobSpec& spec) {
  jobs::JobSpec out;
  out.method = spec.method();
  for (const auto& [name, value] : spec.parameters()) out.parameters[name] = value;
  if (spec.mesh_position_bits() != 0) out.mesh_position_bits = spec.mesh_position_bits();
  return out;
}

render::RenderParams FromProto(const v1::RenderRequest& request) {
  render::RenderParams p;
  if (request.width() != 0) p.width = request.width();
  if (request.height() != 0) p.height = request.height();
  if (request.has_azimuth_deg()) p.camera.azimuth_deg = request.azimuth_deg();
  if (request.has_elevation_deg()) p.camera.elevation_deg = request.elevation_deg();
  if (request.has_distance()) p.camera.distance = request.distance();
  if (request.has_fov_deg()) p.camera.fov_deg = request.fov_deg();
  p.color_attribute = request.color();
  p.color_min = request.color_min();
  p.color_max = request.color_max();
  p.shading = request.flat_shading() ? render::Shading::kFlat : render::Shading::kSmooth;
  p.wireframe = request.wireframe();
  p.transparent = request.transparent();
  if (request.samples() != 0) p.samples = request.samples();
  return p;
}

}  // namespace lsqsurf::server
