#include "server/reconstruction_service.h"

#include <spdlog/spdlog.h>

#include "server/convert.h"
#include "worker/core/strings.h"
#include "worker/jobs/method_registry.h"

namespace lsqsurf::server {
namespace {

// Runs a handler body; an exception becomes a status instead of leaving the gRPC thread.
template <class Body>
grpc::Status Run(const char* rpc, Body&& body) {
  try {
    return body();
  } catch (const std::bad_alloc&) {
    spdlog::error("{}: out of memory", rpc);
    return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, "the server ran out of memory for this call");
  } catch (const std::exception& e) {
    spdlog::error("{}: {}", rpc, e.what());
    return grpc::Status(grpc::StatusCode::INTERNAL, core::StrCat(rpc, " failed: ", e.what()));
  }
}

}  // namespace

template <class Body>
grpc::Status ReconstructionService::Serve(const char* rpc, grpc::ServerContext* context, Body&& body) {
  const auto start = std::chrono::steady_clock::now();
  std::string who;  // For the log: the token's name, else the peer.
  grpc::Status status = Run(rpc, [&] {
    auto caller = Identify(*context);
    if (!caller.ok()) {
      who = core::StrCat("peer ", context->peer());
      return ToGrpcStatus(caller.status());
    }
    who = caller->name.empty() ? core::StrCat("peer ", context->peer()) : core::StrCat("'", caller->name, "'");
    return body(*caller);
  });
  if (!status.ok() && status.error_code() != grpc::StatusCode::CANCELLED) {
    spdlog::info("{} by {} refused ({}): {}", rpc, who,
                 absl::StatusCodeToString(static_cast<absl::StatusCode>(status.error_code())), status.error_message());
  }
  if (calls_ != nullptr) {
    calls_->CallEnded(rpc, status.error_code(),
                      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  }
  return status;
}

absl::StatusOr<Caller> ReconstructionService::Identify(const grpc::ServerContext& context) const {
  if (tokens_ == nullptr) return Caller{};
  const auto& metadata = context.client_metadata();
  const auto header = metadata.find("authorization");
  if (header == metadata.end()) return tokens_->Authenticate("");
  return tokens_->Authenticate(std::string_view(header->second.data(), header->second.size()));
}

absl::StatusOr<jobs::JobRecord> ReconstructionService::Visible(const Caller& caller, const std::string& id) const {
  auto record = jobs_.Get(id);
  if (record.ok() && !caller.admin && record->owner != caller.name) return jobs::NoSuchJob(id);
  return record;
}

grpc::Status ReconstructionService::SubmitJob(grpc::ServerContext* context,
                                              grpc::ServerReader<v1::SubmitJobRequest>* reader, v1::Job* response) {
  return Serve("SubmitJob", context, [&](const Caller& caller) { return Submit(caller, context, reader, response); });
}

grpc::Status ReconstructionService::Submit(const Caller& caller, grpc::ServerContext* context,
                                           grpc::ServerReader<v1::SubmitJobRequest>* reader, v1::Job* response) {
  v1::SubmitJobRequest message;
  if (!reader->Read(&message) || !message.has_spec()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "the first SubmitJob message must carry the job spec");
  }
  auto spec = FromProto(message.spec());  // Fully checked: a bad spec fails before its upload.
  if (!spec.ok()) return ToGrpcStatus(spec.status());
  jobs::Uploads uploads;
  size_t received = 0;
  const int64_t max_upload = jobs_.MaxUploadBytes(caller.submitter);
  const auto limit = static_cast<size_t>(max_upload);
  const bool quota_limit = max_upload < jobs_.options().max_input_bytes;
  while (reader->Read(&message)) {
    if (message.has_spec()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "only the first message may carry a spec");
    }
    const char* slot = message.has_velocity_chunk() ? jobs::kVelocityUpload
                       : message.has_cells_chunk()  ? jobs::kCellsUpload
                                                    : jobs::kInputUpload;
    const std::string& chunk = message.has_velocity_chunk() ? message.velocity_chunk()
                               : message.has_cells_chunk()  ? message.cells_chunk()
                                                            : message.input_chunk();
    if (chunk.size() > kMaxChunkBytes) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "upload chunks must be at most 1 MiB");
    }
    if (received + chunk.size() > limit) {
      return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          core::StrCat("the upload exceeds ", quota_limit ? "your quota's" : "this server's",
                                       " limit of ", limit, " bytes"));
    }
    received += chunk.size();
    uploads[slot] += chunk;
    if (calls_ != nullptr) calls_->Received(static_cast<int64_t>(chunk.size()));
  }
  if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "upload cancelled");
  auto record = jobs_.Submit(*spec, std::move(uploads), caller.submitter);
  if (!record.ok()) return ToGrpcStatus(record.status());
  ToProto(*record, response);
  return grpc::Status::OK;
}

grpc::Status ReconstructionService::WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                                             grpc::ServerWriter<v1::JobEvent>* writer) {
  return Serve("WatchJob", context, [&](const Caller& caller) {
    auto record = Visible(caller, request->job_id());
    if (!record.ok()) return ToGrpcStatus(record.status());
    return Watch(context, *record, writer);
  });
}

grpc::Status ReconstructionService::Watch(grpc::ServerContext* context, const jobs::JobRecord& first,
                                          grpc::ServerWriter<v1::JobEvent>* writer) {
  const std::string id = first.id;
  absl::StatusOr<jobs::JobRecord> record = first;
  for (;;) {
    v1::JobEvent event;
    ToProto(*record, event.mutable_job());
    if (!writer->Write(event)) return grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
    if (jobs::IsTerminal(record->state)) return grpc::Status::OK;
    const uint64_t seen = record->version;
    // Changes wake the wait at once; the timeout only bounds how long a departed client holds
    // this thread.
    do {
      if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "watch cancelled");
      if (jobs_.shutting_down()) {
        return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down; watch again later");
      }
      record = jobs_.WaitForChange(id, seen, std::chrono::milliseconds(500));
      if (!record.ok()) return ToGrpcStatus(record.status());
    } while (record->version == seen);
  }
}

grpc::Status ReconstructionService::GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request,
                                           v1::Job* response) {
  return Serve("GetJob", context, [&](const Caller& caller) {
    auto record = Visible(caller, request->job_id());
    if (!record.ok()) return ToGrpcStatus(record.status());
    ToProto(*record, response);
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                                             v1::ListJobsResponse* response) {
  return Serve("ListJobs", context, [&](const Caller& caller) {
    if (request->limit() < 0) return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "limit must not be negative");
    int count = 0;
    for (const auto& r : jobs_.List()) {
      if (!caller.admin && r.owner != caller.name) continue;
      if (request->limit() > 0 && count++ >= request->limit()) break;
      ToProto(r, response->add_jobs());
    }
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                                              v1::Job* response) {
  return Serve("CancelJob", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    auto record = jobs_.Cancel(request->job_id());
    if (!record.ok()) return ToGrpcStatus(record.status());
    ToProto(*record, response);
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::DeleteJob(grpc::ServerContext* context, const v1::DeleteJobRequest* request,
                                              v1::DeleteJobResponse*) {
  return Serve("DeleteJob", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    return ToGrpcStatus(jobs_.Delete(request->job_id()));
  });
}

grpc::Status ReconstructionService::FetchResult(grpc::ServerContext* context, const v1::FetchResultRequest* request,
                                                grpc::ServerWriter<v1::ResultChunk>* writer) {
  return Serve("FetchResult", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    return Fetch(context, *request, writer);
  });
}

grpc::Status ReconstructionService::Fetch(grpc::ServerContext* context, const v1::FetchResultRequest& request,
                                          grpc::ServerWriter<v1::ResultChunk>* writer) {
  auto reader = jobs_.OpenResult(request.job_id(), request.name());
  if (!reader.ok()) return ToGrpcStatus(reader.status());
  v1::ResultChunk chunk;
  chunk.set_total_bytes((*reader)->size());
  bool first = true;
  for (;;) {
    if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "download cancelled");
    auto data = (*reader)->Next(kMaxChunkBytes);
    if (!data.ok()) return ToGrpcStatus(data.status());
    if (data->empty() && !first) return grpc::Status::OK;
    chunk.set_data(*std::move(data));
    if (!writer->Write(chunk)) return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
    if (calls_ != nullptr) calls_->Sent(static_cast<int64_t>(chunk.data().size()));
    chunk.clear_total_bytes();
    if (chunk.data().empty()) return grpc::Status::OK;  // An empty artifact: one empty chunk.
    first = false;
  }
}

grpc::Status ReconstructionService::Render(grpc::ServerContext* context, const v1::RenderRequest* request,
                                           v1::RenderResponse* response) {
  return Serve("Render", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    auto view = FromProto(request->options());
    if (!view.ok()) return ToGrpcStatus(view.status());
    auto picture = jobs_.Render(request->job_id(), request->name(), *view);
    if (!picture.ok()) return ToGrpcStatus(picture.status());
    if (calls_ != nullptr) {
      calls_->Sent(static_cast<int64_t>(picture->png.size()));
      calls_->FrameRendered();
    }
    response->set_png(std::move(picture->png));
    response->set_color_min(picture->color_min);
    response->set_color_max(picture->color_max);
    response->set_renderer(picture->renderer);
    response->set_grid_rms_error(picture->grid_rms_error);
    response->set_grid_max_error(picture->grid_max_error);
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::ListMethods(grpc::ServerContext* context, const v1::ListMethodsRequest*,
                                                v1::ListMethodsResponse* response) {
  return Serve("ListMethods", context, [&](const Caller&) {
    for (const auto& m : jobs::Methods()) {
      v1::Method* out = response->add_methods();
      out->set_name(m.info.name);
      out->set_description(m.info.description);
      for (const auto& a : m.info.attributes) out->add_attributes(a);
      for (const auto& p : m.info.defaults.Describe()) ToProto(p, out->add_parameters());
    }
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::GetServerInfo(grpc::ServerContext* context, const v1::GetServerInfoRequest*,
                                                  v1::ServerInfo* response) {
  return Serve("GetServerInfo", context, [&](const Caller& caller) {
    const jobs::JobServiceOptions& o = jobs_.options();
    response->set_version(LSQSURF_VERSION);
    response->set_max_points(o.max_points);
    response->set_max_cells(o.max_cells);
    response->set_min_points(o.min_points);
    response->set_max_upload_bytes(o.max_input_bytes);
    response->set_max_chunk_bytes(static_cast<int64_t>(kMaxChunkBytes));
    response->set_max_queue(o.max_queue);
    response->set_workers(o.workers);
    response->set_max_renders(o.max_renders);
    response->set_can_render(jobs_.CanRender());
    response->set_requires_token(tokens_ != nullptr);
    response->set_retain_seconds(o.retain.count());
    response->set_max_store_bytes(o.max_store_bytes);
    if (caller.admin) response->set_stored_bytes(jobs_.StoredBytes());
    v1::Account* account = response->mutable_account();
    account->set_name(caller.name);
    account->set_admin(caller.admin);
    account->set_max_jobs(caller.submitter.max_active_jobs);
    account->set_max_stored_bytes(caller.submitter.max_stored_bytes);
    account->set_max_upload_bytes(caller.submitter.max_upload_bytes);
    const jobs::JobService::Usage usage = jobs_.UsageOf(caller.submitter.owner);
    account->set_active_jobs(usage.active_jobs);
    account->set_stored_bytes(usage.stored_bytes);
    return grpc::Status::OK;
  });
}

}  // namespace lsqsurf::server
