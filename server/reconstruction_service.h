// server/reconstruction_service.h — the gRPC face of the job service.
//
// Each handler converts, validates, calls the job service and converts the status once; every
// handler is guarded, so an exception (an allocation failure included) answers INTERNAL or
// RESOURCE_EXHAUSTED and the server lives on. The synchronous gRPC API is used: a handler holds
// a gRPC thread only while it streams bytes or waits for job events (WatchJob), never while an
// engine runs. The server knows the API and the job service, never files, decoders or the
// renderer.
//
// With a token table, every call of this API needs a token (health and reflection are other
// services and stay open): a user sees and acts on its own jobs only, and another user's job
// answers NOT_FOUND exactly as a missing one does, so ids leak nothing; an admin sees all. Every
// refusal is logged with the token's name (or the peer's address when there is no valid token).
#pragma once

#include <cstdint>
#include <string>

#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "server/metrics.h"
#include "server/tokens.h"
#include "worker/jobs/job_service.h"

namespace lsqsurf::server {

class ReconstructionService final : public v1::Reconstruction::Service {
 public:
  // `jobs`, `calls` and `tokens` must outlive the service; `calls` may be null, and `tokens`
  // null serves everyone as an admin.
  explicit ReconstructionService(jobs::JobService& jobs, CallObserver* calls = nullptr,
                                 const TokenTable* tokens = nullptr)
      : jobs_(jobs), calls_(calls), tokens_(tokens) {}

  grpc::Status SubmitJob(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                         v1::Job* response) override;
  grpc::Status WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                        grpc::ServerWriter<v1::JobEvent>* writer) override;
  grpc::Status GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request, v1::Job* response) override;
  grpc::Status ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                        v1::ListJobsResponse* response) override;
  grpc::Status CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request, v1::Job* response) override;
  grpc::Status DeleteJob(grpc::ServerContext* context, const v1::DeleteJobRequest* request,
                         v1::DeleteJobResponse* response) override;
  grpc::Status FetchResult(grpc::ServerContext* context, const v1::FetchResultRequest* request,
                           grpc::ServerWriter<v1::ResultChunk>* writer) override;
  grpc::Status ListMethods(grpc::ServerContext* context, const v1::ListMethodsRequest* request,
                           v1::ListMethodsResponse* response) override;
  grpc::Status Render(grpc::ServerContext* context, const v1::RenderRequest* request,
                      v1::RenderResponse* response) override;
  grpc::Status GetServerInfo(grpc::ServerContext* context, const v1::GetServerInfoRequest* request,
                             v1::ServerInfo* response) override;

  static constexpr size_t kMaxChunkBytes = size_t{1} << 20;
  // The name the health service reports this API under.
  static constexpr char kServiceName[] = "lsqsurf.v1.Reconstruction";

 private:
  // Runs a handler's body for the call's caller: identifies it, times the call, turns an
  // exception into a status and logs a refusal.
  template <class Body>
  grpc::Status Serve(const char* rpc, grpc::ServerContext* context, Body&& body);
  absl::StatusOr<Caller> Identify(const grpc::ServerContext& context) const;
  // The job if the caller may see it; kNotFound otherwise, as for a missing one.
  absl::StatusOr<jobs::JobRecord> Visible(const Caller& caller, const std::string& id) const;
  grpc::Status Submit(const Caller& caller, grpc::ServerContext* context,
                      grpc::ServerReader<v1::SubmitJobRequest>* reader, v1::Job* response);
  grpc::Status Watch(grpc::ServerContext* context, const jobs::JobRecord& first,
                     grpc::ServerWriter<v1::JobEvent>* writer);
  grpc::Status Fetch(grpc::ServerContext* context, const v1::FetchResultRequest& request,
                     grpc::ServerWriter<v1::ResultChunk>* writer);

  jobs::JobService& jobs_;
  CallObserver* calls_;
  const TokenTable* tokens_;
};

}  // namespace lsqsurf::server
