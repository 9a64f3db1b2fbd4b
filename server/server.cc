#include "server/server.h"

#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/resource_quota.h>
#include <spdlog/spdlog.h>

#include "worker/core/strings.h"

namespace lsqsurf::server {

Server::Server(jobs::JobService& jobs, const ServerOptions& options)
    : jobs_(jobs), host_(options.listen.substr(0, options.listen.rfind(':'))) {
  service_ = std::make_unique<ReconstructionService>(jobs, options.calls, options.tokens, options.streams);
  reflection_ = std::make_unique<ReflectionService>(
      std::vector<std::string>{ReconstructionService::kServiceName, "grpc.health.v1.Health",
                               ReflectionService::kServiceName},
      service_->streams());
}

absl::StatusOr<std::unique_ptr<Server>> Server::Start(jobs::JobService& jobs, ServerOptions options) {
  std::unique_ptr<Server> server(new Server(jobs, options));
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  auto credentials = options.credentials != nullptr ? options.credentials : grpc::InsecureServerCredentials();
  builder.AddListeningPort(options.listen, credentials, &server->port_);
  builder.RegisterService(server->service_.get());
  builder.RegisterService(server->reflection_.get());
  builder.SetMaxReceiveMessageSize(options.max_message_bytes);
  builder.SetMaxSendMessageSize(options.max_message_bytes);
  builder.AddChannelArgument(GRPC_ARG_MAX_CONCURRENT_STREAMS, options.max_streams_per_connection);
  // The synchronous calls' threads are bounded; the streams run on the callback API and hold none.
  grpc::ResourceQuota quota("lsqsurfd");
  quota.SetMaxThreads(options.max_threads);
  builder.SetResourceQuota(quota);
  server->server_ = builder.BuildAndStart();
  if (server->server_ == nullptr || server->port_ == 0) {
    return absl::UnavailableError(core::StrCat("cannot listen on ", options.listen));
  }
  server->server_->GetHealthCheckService()->SetServingStatus(ReconstructionService::kServiceName, true);
  server->readiness_ =
      std::thread([s = server.get(), period = options.readiness_period] { s->FollowReadiness(period); });
  return server;
}

Server::~Server() { Shutdown(); }

std::shared_ptr<grpc::Channel> Server::InProcessChannel() {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(16 << 20);
  return server_->InProcessChannel(args);
}

std::string Server::address() const { return core::StrCat(host_, ":", port_); }

void Server::FollowReadiness(std::chrono::milliseconds period) {
  bool serving = true;
  std::unique_lock lock(mutex_);
  while (!stop_wake_.wait_for(lock, period, [this] { return stopping_; })) {
    const bool reachable = jobs_.StoreReachable();
    if (reachable == serving) continue;
    serving = reachable;
    server_->GetHealthCheckService()->SetServingStatus(ReconstructionService::kServiceName, serving);
    spdlog::log(serving ? spdlog::level::info : spdlog::level::warn, "the job store is {}",
                serving ? "reachable again: serving" : "unreachable: reporting not serving");
  }
}

void Server::Drain() {
  std::call_once(drain_once_, [&] {
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
    }
    stop_wake_.notify_all();
    if (readiness_.joinable()) readiness_.join();
    server_->GetHealthCheckService()->SetServingStatus(false);
    // Interrupted jobs go back to the queue in the store first, then open streams are closed.
    jobs_.Shutdown();
  });
}

void Server::Shutdown(std::chrono::system_clock::time_point deadline) {
  std::call_once(shutdown_once_, [&] {
    Drain();
    server_->Shutdown(deadline);
  });
}

void Server::Wait() { server_->Wait(); }

}  // namespace lsqsurf::server
