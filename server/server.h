// server/server.h — lsqsurfd's gRPC server: the API, health and reflection services on one
// listening port, with the bounds that keep it alive under any client.
//
// Started the same way by `lsqsurfd` and by the tests, so that what the tests talk to is what
// users talk to: streams on the callback API (no thread held per open stream), the synchronous
// calls on a bounded thread pool, a per-connection stream limit and the message size limits.
// Readiness (the API's health status) follows the job store; liveness does not.
#pragma once

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/statusor.h"
#include "server/reconstruction_service.h"
#include "server/reflection.h"

namespace lsqsurf::server {

struct ServerOptions {
  // HOST:PORT to listen on; port 0 picks a free one (see Server::port()).
  std::string listen = "127.0.0.1:0";
  // Null: plaintext.
  std::shared_ptr<grpc::ServerCredentials> credentials;
  // Null: every caller is served as an admin, without a token. Must outlive the server.
  const TokenTable* tokens = nullptr;
  // Told about every call; may be null. Must outlive the server.
  CallObserver* calls = nullptr;
  StreamLimits streams;
  // Concurrent calls one client connection may have open.
  int max_streams_per_connection = 100;
  // Threads gRPC may run the synchronous calls on; past it calls are refused.
  int max_threads = 64;
  // Largest message either way; uploads and results are chunked well below it.
  int max_message_bytes = 16 << 20;
  // How often readiness is checked against the store.
  std::chrono::milliseconds readiness_period{500};
};

class Server {
 public:
  // Starts serving `jobs`, which must outlive the server. Errors: kUnavailable when the address
  // cannot be bound.
  static absl::StatusOr<std::unique_ptr<Server>> Start(jobs::JobService& jobs, ServerOptions options);
  ~Server();  // Calls Shutdown() with no grace.
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  int port() const { return port_; }
  // The address clients reach it at: the listening host and the bound port.
  std::string address() const;
  ReconstructionService& service() { return *service_; }
  // A channel to this server within the process (the HTTP gateway's): no socket and no TLS, but
  // every call is checked as a network one is (tokens, limits).
  std::shared_ptr<grpc::Channel> InProcessChannel();

  // Reports not serving and returns the running jobs to the queue in the store: nothing
  // accepted is lost past this point. Calls are still answered. Idempotent.
  void Drain();
  // Drain(), then closes the open calls, waiting for them until `deadline`. Idempotent.
  void Shutdown(std::chrono::system_clock::time_point deadline = std::chrono::system_clock::now());
  // Blocks until Shutdown() has finished.
  void Wait();

 private:
  Server(jobs::JobService& jobs, const ServerOptions& options);
  void FollowReadiness(std::chrono::milliseconds period);

  jobs::JobService& jobs_;
  std::string host_;
  int port_ = 0;
  std::unique_ptr<ReconstructionService> service_;
  std::unique_ptr<ReflectionService> reflection_;
  std::unique_ptr<grpc::Server> server_;
  std::mutex mutex_;
  std::condition_variable stop_wake_;
  bool stopping_ = false;  // mutex_
  std::once_flag drain_once_, shutdown_once_;
  std::thread readiness_;
};

}  // namespace lsqsurf::server
