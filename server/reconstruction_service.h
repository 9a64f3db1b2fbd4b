// server/reconstruction_service.h — the gRPC face of the job service.
//
// Each handler converts, validates, calls the job service and converts the status once; every
// handler is guarded, so an exception (an allocation failure included) answers INTERNAL or
// RESOURCE_EXHAUSTED and the server lives on. The server knows the API and the job service,
// never decoders or the renderer.
//
// Threads: the streaming calls (SubmitJob, WatchJob, FetchResult) run on gRPC's callback API, so
// an open stream holds no thread, whatever its client does; each is admitted by the StreamGuard
// (bounded in number, per user, and cancelled when idle). An upload's chunks go to a spool file
// as they arrive, so a stalled upload holds disk, not memory; a finished one is decoded and
// submitted on one of a few submission threads. One thread follows the job service's changes for
// every watcher. The unary calls are synchronous and short (Render is bounded by its slots).
//
// With a token table, every call of this API needs a token (health and reflection are other
// services and stay open): a user sees and acts on its own jobs only, and another user's job
// answers NOT_FOUND exactly as a missing one does, so ids leak nothing; an admin sees all. Every
// refusal is logged with the token's name (or the peer's address when there is no valid token).
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "server/metrics.h"
#include "server/streams.h"
#include "server/tokens.h"
#include "worker/jobs/job_service.h"

namespace lsqsurf::server {

using ReconstructionBase =
    v1::Reconstruction::WithCallbackMethod_SubmitJob<v1::Reconstruction::WithCallbackMethod_WatchJob<
        v1::Reconstruction::WithCallbackMethod_FetchResult<v1::Reconstruction::Service>>>;

class ReconstructionService final : public ReconstructionBase {
 public:
  // `jobs`, `calls` and `tokens` must outlive the service, and the service must be destroyed
  // before `jobs` (its watcher thread follows the job service); `calls` may be null, and
  // `tokens` null serves everyone as an admin. Uploads are spooled under the job service's data
  // directory.
  explicit ReconstructionService(jobs::JobService& jobs, CallObserver* calls = nullptr,
                                 const TokenTable* tokens = nullptr, StreamLimits limits = {});
  ~ReconstructionService() override;

  grpc::ServerReadReactor<v1::SubmitJobRequest>* SubmitJob(grpc::CallbackServerContext* context,
                                                           v1::Job* response) override;
  grpc::ServerWriteReactor<v1::JobEvent>* WatchJob(grpc::CallbackServerContext* context,
                                                   const v1::WatchJobRequest* request) override;
  grpc::ServerWriteReactor<v1::ResultChunk>* FetchResult(grpc::CallbackServerContext* context,
                                                         const v1::FetchResultRequest* request) override;
  grpc::Status GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request, v1::Job* response) override;
  grpc::Status ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                        v1::ListJobsResponse* response) override;
  grpc::Status CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request, v1::Job* response) override;
  grpc::Status DeleteJob(grpc::ServerContext* context, const v1::DeleteJobRequest* request,
                         v1::DeleteJobResponse* response) override;
  grpc::Status ListMethods(grpc::ServerContext* context, const v1::ListMethodsRequest* request,
                           v1::ListMethodsResponse* response) override;
  grpc::Status Render(grpc::ServerContext* context, const v1::RenderRequest* request,
                      v1::RenderResponse* response) override;
  grpc::Status GetServerInfo(grpc::ServerContext* context, const v1::GetServerInfoRequest* request,
                             v1::ServerInfo* response) override;

  // The bounds on streams, shared with the reflection service.
  StreamGuard& streams() { return streams_; }

  static constexpr size_t kMaxChunkBytes = size_t{1} << 20;
  // The longest error message sent or logged; longer ones are cut, saying so.
  static constexpr size_t kMaxMessageBytes = 1024;
  // The name the health service reports this API under.
  static constexpr char kServiceName[] = "lsqsurf.v1.Reconstruction";

 private:
  class Upload;
  class Watch;
  class Download;
  // What a call's end reports: its rpc, who made it, when it began.
  struct CallRecord {
    const char* rpc;
    std::string who = {};
    std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now();
  };

  // Runs a unary handler's body for the call's caller: identifies it, times the call, turns an
  // exception into a status and logs a refusal.
  template <class Body>
  grpc::Status Serve(const char* rpc, grpc::ServerContext* context, Body&& body);
  // A streaming call let in: its caller (named in `call`), the job it names if any (visible to
  // the caller), and its place among the open streams. Errors: the refusal to answer with.
  struct Admitted {
    Caller caller;
    std::optional<jobs::JobRecord> job;
    std::unique_ptr<StreamGuard::Ticket> ticket;
  };
  absl::StatusOr<Admitted> Admit(grpc::CallbackServerContext* context, CallRecord& call, StreamKind kind,
                                 const std::string* job_id);
  // The status a call ends with: its message bounded and made printable, a refusal logged, the
  // call counted.
  grpc::Status Conclude(const CallRecord& call, grpc::Status status) const;
  absl::StatusOr<Caller> Identify(const grpc::ServerContextBase& context) const;
  // The job if the caller may see it; kNotFound otherwise, as for a missing one; kInvalidArgument
  // for a text that is no job id.
  absl::StatusOr<jobs::JobRecord> Visible(const Caller& caller, const std::string& id) const;
  // Room in the spool for `bytes` more of `caller`'s upload (SpoolLedger::Reserve).
  absl::Status ReserveSpool(const Caller& caller, int64_t bytes);
  // Runs `task` on a submission thread (a finished upload's decoding and submission).
  void Post(std::function<void()> task, size_t upload_bytes);
  // `small_only`: the thread kept for uploads under kSmallUploadBytes.
  void SubmitLoop(bool small_only);
  void WatchLoop();
  void RemoveWatch(Watch* watch);

  jobs::JobService& jobs_;
  CallObserver* calls_;
  const TokenTable* tokens_;
  StreamGuard streams_;
  const std::string spool_dir_;  // Uploads in progress, one file per slot.
  SpoolLedger spool_;            // Their bytes, by user.

  std::mutex submit_mutex_;
  std::condition_variable submit_wake_;
  std::deque<std::function<void()>> submissions_, small_submissions_;  // By upload size.
  bool stopping_ = false;                                              // submit_mutex_.
  std::vector<std::thread> submit_threads_;

  // Recursive: a watcher's reactions (its end, and so its removal) may run on the thread that
  // pokes it.
  std::recursive_mutex watch_mutex_;
  std::set<Watch*> watches_;
  std::atomic<bool> stop_watching_{false};
  std::thread watch_thread_;
};

}  // namespace lsqsurf::server
