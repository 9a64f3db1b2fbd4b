// server/http_gateway.h — lsqsurfd's web face (--http-listen): the job page and a small read-only
// JSON API behind it, on the bounded HTTP front of http_front.h (GNU libmicrohttpd).
//
// The API answers through the gRPC service itself, over an in-process channel, with the token the
// browser sends (Authorization: Bearer) passed on as gRPC's: what a user may see, the limits and
// the refusals are the gRPC API's, with no second path to anyone's data. Routes (GET and HEAD;
// any other method is answered 405):
//   /, /jobs/ID                     the page (it routes itself)
//   /static/...                     its scripts, styles and libraries (three.js, Draco's decoder)
//   /api/jobs?limit=N//   /api/jobs?limit=N               ListJobs as JSON (lsqsurf.v1 field names)page_token=T
//   ListJobs as JSON (lsqsurf.v1 field names), a page at a time /api/jobs/ID                    GetJob
//   /api/jobs/ID/results/NAME       FetchResult, streamed
//   /api/methods                    ListMethods
// Errors answer JSON {"code": "NOT_FOUND", "message": ...} with the matching HTTP status.
#pragma once

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "server/http_front.h"

namespace lsqsurf::server {

class HttpGateway {
 public:
  // Serves the API through `channel` (the gRPC server's in-process channel), on a front with
  // `options`' address, TLS files, host names and limits. Errors: as HttpFront::Start.
  static absl::StatusOr<std::unique_ptr<HttpGateway>> Start(std::shared_ptr<grpc::Channel> channel,
                                                            const HttpFrontOptions& options);
  ~HttpGateway();  // Stops serving.
  HttpGateway(const HttpGateway&) = delete;
  HttpGateway& operator=(const HttpGateway&) = delete;

  // "http://HOST:PORT" or "https://HOST:PORT".
  std::string address() const;
  void Stop();

 private:
  HttpGateway() = default;

  std::unique_ptr<HttpFront> front_;
  std::string scheme_, host_;
  int port_ = 0;
};

}  // namespace lsqsurf::server
