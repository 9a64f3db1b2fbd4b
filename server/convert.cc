#include "server/convert.h"

#include "worker/core/strings.h"

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
  if (r.spec.preview.enabled) {
    v1::PreviewSpec* preview = out->mutable_spec()->mutable_preview();
    ToProto(r.spec.preview.render, preview->mutable_options());
    preview->set_turntable_deg_per_frame(r.spec.preview.turntable_deg_per_frame);
  }
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

absl::StatusOr<jobs::JobSpec> FromProto(const v1::JobSpec& spec) {
  jobs::JobSpec out;
  out.method = spec.method();
  for (const auto& [name, value] : spec.parameters()) out.parameters[name] = value;
  if (spec.mesh_position_bits() != 0) out.mesh_position_bits = spec.mesh_position_bits();
  if (spec.has_preview()) {
    auto render = FromProto(spec.preview().options());
    if (!render.ok()) return absl::InvalidArgumentError(core::StrCat("preview: ", render.status().message()));
    out.preview.enabled = true;
    out.preview.render = *std::move(render);
    out.preview.turntable_deg_per_frame = spec.preview().turntable_deg_per_frame();
  }
  return out;
}

absl::StatusOr<render::RenderParams> FromProto(const v1::RenderOptions& o) {
  render::RenderParams p;
  if (o.width() != 0) p.width = o.width();
  if (o.height() != 0) p.height = o.height();
  if (o.has_azimuth_deg()) p.camera.azimuth_deg = o.azimuth_deg();
  if (o.has_elevation_deg()) p.camera.elevation_deg = o.elevation_deg();
  if (o.has_distance()) p.camera.distance = o.distance();
  if (o.has_fov_deg()) p.camera.fov_deg = o.fov_deg();
  if (!o.up_axis().empty()) {
    auto up = render::ParseUpAxis(o.up_axis());
    if (!up.ok()) return up.status();
    p.camera.up = *up;
  }
  p.color_attribute = o.color();
  p.color_min = o.color_min();
  p.color_max = o.color_max();
  p.shading = o.flat_shading() ? render::Shading::kFlat : render::Shading::kSmooth;
  p.wireframe = o.wireframe();
  p.transparent = o.transparent();
  if (o.samples() != 0) p.samples = o.samples();
  return p;
}

void ToProto(const render::RenderParams& p, v1::RenderOptions* out) {
  out->set_width(p.width);
  out->set_height(p.height);
  out->set_azimuth_deg(p.camera.azimuth_deg);
  out->set_elevation_deg(p.camera.elevation_deg);
  if (p.camera.distance > 0) out->set_distance(p.camera.distance);
  out->set_fov_deg(p.camera.fov_deg);
  out->set_up_axis(p.camera.up == render::UpAxis::kX ? "x" : p.camera.up == render::UpAxis::kY ? "y" : "z");
  out->set_color(p.color_attribute);
  out->set_color_min(p.color_min);
  out->set_color_max(p.color_max);
  out->set_flat_shading(p.shading == render::Shading::kFlat);
  out->set_wireframe(p.wireframe);
  out->set_transparent(p.transparent);
  out->set_samples(p.samples);
}

}  // namespace lsqsurf::server
