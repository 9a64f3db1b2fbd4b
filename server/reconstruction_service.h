// server/reconstruction_service.h — the gRPC face of the job service.
//
// Each handler converts, validates, calls the job service and converts the status once. The
// synchronous gRPC API is used: a handler holds a gRPC thread only while it streams bytes or
// waits for job events (WatchJob), never while an engine runs. Engine work happens on the job
// service's worker threads.
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <string>

#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "worker/jobs/job_service.h"
#include "worker/render/render.h"

namespace lsqsurf::server {

class ReconstructionService final : public v1::Reconstruction::Service {
 public:
  // `jobs` must outlive the service.
  explicit ReconstructionService(jobs::JobService& jobs) : jobs_(jobs) {}

  grpc::Status SubmitJob(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                         v1::Job* response) override;
  grpc::Status WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                        grpc::ServerWriter<v1::JobEvent>* writer) override;
  grpc::Status GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request,
                      v1::Job* response) override;
  grpc::Status ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                        v1::ListJobsResponse* response) override;
  grpc::Status CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                         v1::Job* response) override;
  grpc::Status DeleteJob(grpc::ServerContext* context, const v1::DeleteJobRequest* request,
                         v1::DeleteJobResponse* response) override;
  grpc::Status FetchResult(grpc::ServerContext* context, const v1::FetchResultRequest* request,
                           grpc::ServerWriter<v1::ResultChunk>* writer) override;
  grpc::Status ListMethods(grpc::ServerContext* context, const v1::ListMethodsRequest* request,
                           v1::ListMethodsResponse* response) override;
  grpc::Status Render(grpc::ServerContext* context, const v1::RenderRequest* request,
                      v1::RenderResponse* response) override;

  static constexpr size_t kMaxChunkBytes = size_t{1} << 20;

 private:
  // The path of an artifact of a job; an empty name means the job's first result.
  absl::StatusOr<std::string> ArtifactPath(const std::string& job_id, const std::string& name) const;

  jobs::JobService& jobs_;
};

}  // namespace lsqsurf::server
