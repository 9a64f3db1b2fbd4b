// server/http_gateway.h — lsqsurfd's web face (--http-listen): the job page and a small read-only
// JSON API behind it, on an embedded HTTP server (cpp-httplib).
//
// The API answers through the gRPC service itself, over an in-process channel, with the token the
// browser sends (Authorization: Bearer) passed on as gRPC's: what a user may see, the limits and
// the refusals are the gRPC API's, with no second path to anyone's data. Routes (GET only):
//   /, /jobs/ID                     the page (it routes itself)
//   /static/...                     its scripts, styles and libraries (three.js, Draco's decoder)
//   /api/jobs?limit=N               ListJobs as JSON (lsqsurf.v1 field names)
//   /api/jobs/ID                    GetJob
//   /api/jobs/ID/results/NAME       FetchResult, streamed
//   /api/methods                    ListMethods
// Errors answer JSON {"code": "NOT_FOUND", "message": ...} with the matching HTTP status.
#pragma once

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>
#include <thread>

#include "absl/status/statusor.h"

namespace httplib {
class Server;
}

namespace lsqsurf::server {

struct HttpOptions {
  // HOST:PORT; port 0 picks a free one (HttpGateway::address()).
  std::string listen = "127.0.0.1:0";
  // PEM files to serve HTTPS with; both empty: plain HTTP.
  std::string tls_cert_path;
  std::string tls_key_path;
  // Requests served at once; more wait for a thread.
  int threads = 8;
};

class HttpGateway {
 public:
  // Serves the API through `channel` (the gRPC server's in-process channel). Errors:
  // kInvalidArgument (a malformed address), kUnavailable (cannot bind, or the TLS files do not
  // load).
  static absl::StatusOr<std::unique_ptr<HttpGateway>> Start(std::shared_ptr<grpc::Channel> channel,
                                                            const HttpOptions& options);
  ~HttpGateway();  // Stops serving.
  HttpGateway(const HttpGateway&) = delete;
  HttpGateway& operator=(const HttpGateway&) = delete;

  // "http://HOST:PORT" or "https://HOST:PORT".
  std::string address() const;
  void Stop();

 private:
  HttpGateway() = default;
  void Route(std::shared_ptr<grpc::Channel> channel);

  std::unique_ptr<httplib::Server> http_;
  std::string scheme_, host_;
  int port_ = 0;
  std::thread listener_;
};

}  // namespace lsqsurf::server
