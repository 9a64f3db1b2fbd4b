#include "server/reconstruction_service.h"

#include <spdlog/spdlog.h>

#include "server/convert.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace lsqsurf::server {

grpc::Status ReconstructionService::SubmitJob(grpc::ServerContext* context,
                                              grpc::ServerReader<v1::SubmitJobRequest>* reader,
                                              v1::Job* response) {
  v1::SubmitJobRequest message;
  if (!reader->Read(&message) || !message.has_spec()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "the first SubmitJob message must carry the job spec");
  }
  auto converted = FromProto(message.spec());
  if (!converted.ok()) return ToGrpcStatus(converted.status());
  const jobs::JobSpec& spec = *converted;
  // Reject a bad spec before taking the upload.
  if (absl::Status s = jobs::ValidateRequest(spec.method, spec.parameters); !s.ok()) {
    return ToGrpcStatus(s);
  }
  std::string input, velocity;
  const auto limit = static_cast<size_t>(jobs_.options().max_input_bytes);
  while (reader->Read(&message)) {
    if (message.has_spec()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "only the first message may carry a spec");
    }
    const bool is_velocity = message.has_velocity_chunk();
    const std::string& chunk = is_velocity ? message.velocity_chunk() : message.input_chunk();
    if (chunk.size() > kMaxChunkBytes) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "upload chunks must be at most 1 MiB");
    }
    if (input.size() + velocity.size() + chunk.size() > limit) {
      return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          core::StrCat("the upload exceeds this server's limit of ", limit, " bytes"));
    }
    (is_velocity ? velocity : input) += chunk;
  }
  if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "upload cancelled");
  auto record = jobs_.Submit(spec, std::move(input), std::move(velocity));
  if (!record.ok()) {
    spdlog::info("rejected a job from {}: {}", context->peer(), record.status().ToString());
    return ToGrpcStatus(record.status());
  }
  ToProto(*record, response);
  return grpc::Status::OK;
}

grpc::Status ReconstructionService::WatchJob(grpc::ServerContext* context,
                                             const v1::WatchJobRequest* request,
                                             grpc::ServerWriter<v1::JobEvent>* writer) {
  auto record = jobs_.Get(request->job_id());
  if (!record.ok()) return ToGrpcStatus(record.status());
  for (;;) {
    v1::JobEvent event;
    ToProto(*record, event.mutable_job());
    if (!writer->Write(event)) return grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
    if (jobs::IsTerminal(record->state)) return grpc::Status::OK;
    const uint64_t seen = record->version;
    // Short waits keep a departed client from holding this thread for long.
    do {
      if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "watch cancelled");
      if (jobs_.shutting_down()) {
        return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down; watch again later");
      }
      record = jobs_.WaitForChange(request->job_id(), seen, std::chrono::milliseconds(500));
      if (!record.ok()) return ToGrpcStatus(record.status());
    } while (record->version == seen);
  }
}

grpc::Status ReconstructionService::GetJob(grpc::ServerContext*, const v1::GetJobRequest* request,
                                           v1::Job* response) {
  auto record = jobs_.Get(request->job_id());
  if (!record.ok()) return ToGrpcStatus(record.status());
  ToProto(*record, response);
  return grpc::Status::OK;
}

grpc::Status ReconstructionService::ListJobs(grpc::ServerContext*, const v1::ListJobsRequest* request,
                                             v1::ListJobsResponse* response) {
  if (request->limit() < 0) return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "limit must not be negative");
  int count = 0;
  for (const auto& r : jobs_.List()) {
    if (request->limit() > 0 && count++ >= request->limit()) break;
    ToProto(r, response->add_jobs());
  }
  return grpc::Status::OK;
}

grpc::Status ReconstructionService::CancelJob(grpc::ServerContext*, const v1::CancelJobRequest* request,
                                              v1::Job* response) {
  auto record = jobs_.Cancel(request->job_id());
  if (!record.ok()) return ToGrpcStatus(record.status());
  ToProto(*record, response);
  return grpc::Status::OK;
}

grpc::Status ReconstructionService::DeleteJob(grpc::ServerContext*, const v1::DeleteJobRequest* request,
                                              v1::DeleteJobResponse*) {
  return ToGrpcStatus(jobs_.Delete(request->job_id()));
}

grpc::Status ReconstructionService::FetchResult(grpc::ServerContext* context,
                                                const v1::FetchResultRequest* request,
                                                grpc::ServerWriter<v1::ResultChunk>* writer) {
  auto path = ArtifactPath(request->job_id(), request->name());
  if (!path.ok()) return ToGrpcStatus(path.status());
  auto bytes = io::ReadFileBytes(*path);
  if (!bytes.ok()) return ToGrpcStatus(bytes.status());
  v1::ResultChunk chunk;
  chunk.set_total_bytes(static_cast<int64_t>(bytes->size()));
  for (size_t offset = 0; offset < bytes->size() || offset == 0; offset += kMaxChunkBytes) {
    if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "download cancelled");
    chunk.set_data(bytes->substr(offset, kMaxChunkBytes));
    if (!writer->Write(chunk)) return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
    chunk.clear_total_bytes();
    if (bytes->empty()) break;
  }
  return grpc::Status::OK;
}

absl::StatusOr<std::string> ReconstructionService::ArtifactPath(const std::string& job_id,
                                                               const std::string& name) const {
  if (!name.empty()) return jobs_.ResultPath(job_id, name);
  auto record = jobs_.Get(job_id);
  if (!record.ok()) return record.status();
  return jobs_.ResultPath(job_id, record->results.empty() ? "mesh.drc" : record->results.front());
}

grpc::Status ReconstructionService::Render(grpc::ServerContext*, const v1::RenderRequest* request,
                                           v1::RenderResponse* response) {
  auto params = FromProto(request->options());
  if (!params.ok()) return ToGrpcStatus(params.status());
  const render::RenderParams& p = *params;
  // Checked before any file is read or a context is made.
  if (absl::Status s = render::Validate(p); !s.ok()) return ToGrpcStatus(s);
  auto path = ArtifactPath(request->job_id(), request->name());
  if (!path.ok()) return ToGrpcStatus(path.status());
  auto bytes = io::ReadFileBytes(*path);
  if (!bytes.ok()) return ToGrpcStatus(bytes.status());
  auto renderer = jobs_.renderer().Get();
  if (!renderer.ok()) return ToGrpcStatus(renderer.status());
  render::RenderInfo info;
  absl::StatusOr<render::Image> image = absl::InvalidArgumentError("");
  if (auto mesh = io::DecodeDracoMesh(*bytes); mesh.ok() && !mesh->faces.empty()) {
    image = (*renderer)->RenderMesh(*mesh, p, &info);
  } else if (auto cloud = io::DecodeDracoPointCloud(*bytes); cloud.ok()) {
    image = (*renderer)->RenderPoints(*cloud, p, &info);
  } else {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        core::StrCat("artifact '", request->name(), "' is not a Draco mesh or point set; only those can be rendered"));
  }
  if (!image.ok()) return ToGrpcStatus(image.status());
  auto png = render::EncodePng(*image);
  if (!png.ok()) return ToGrpcStatus(png.status());
  response->set_png(*std::move(png));
  response->set_color_min(info.color_min);
  response->set_color_max(info.color_max);
  response->set_renderer(info.renderer);
  return grpc::Status::OK;
}

grpc::Status ReconstructionService::ListMethods(grpc::ServerContext*, const v1::ListMethodsRequest*,
                                                v1::ListMethodsResponse* response) {
  for (const auto& m : jobs::SurfaceMethods()) {
    v1::Method* out = response->add_methods();
    out->set_name(m.name);
    out->set_description(m.description);
    for (const auto& a : m.attributes) out->add_attributes(a);
    for (const auto& p : m.parameters) {
      v1::Parameter* param = out->add_parameters();
      param->set_name(p.name);
      param->set_default_value(p.default_value);
      param->set_min_value(p.min_value);
      param->set_max_value(p.max_value);
      param->set_integer(p.integer);
      param->set_help(p.help);
    }
  }
  return grpc::Status::OK;
}

}  // namespace lsqsurf::server
