// server/reconstruction_service.h — the gRPC face of the job service.
//
// Each handler converts, validates, calls the job service and converts the status once; every
// handler is guarded, so an exception (an allocation failure included) answers INTERNAL or
// RESOURCE_EXHAUSTED and the server lives on. The synchronous gRPC API is used: a handler holds
// a gRPC thread only while it streams bytes or waits for job events (WatchJob), never while an
// engine runs. The server knows the API and the job service, never files, decoders or the
// renderer.
#pragma once

#include <cstdint>
#include <string>

#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "server/metrics.h"
#include "worker/jobs/job_service.h"

namespace lsqsurf::server {

class ReconstructionService final : public v1::Reconstruction::Service {
 public:
  // `jobs` (and `calls`, which may be null) must outlive the service.
  explicit ReconstructionService(jobs::JobService& jobs, CallObserver* calls = nullptr) : jobs_(jobs), calls_(calls) {}

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
  grpc::Status Submit(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                      v1::Job* response);
  grpc::Status Watch(grpc::ServerContext* context, const std::string& id, grpc::ServerWriter<v1::JobEvent>* writer);
  grpc::Status Fetch(grpc::ServerContext* context, const v1::FetchResultRequest& request,
                     grpc::ServerWriter<v1::ResultChunk>* writer);

  jobs::JobService& jobs_;
  CallObserver* calls_;
};

}  // namespace lsqsurf::server
