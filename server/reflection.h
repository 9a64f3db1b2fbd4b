// server/reflection.h — gRPC server reflection (grpc.reflection.v1alpha, what grpcurl and grpcui
// ask), served on the callback API.
//
// libgrpc++_reflection's service is synchronous: each open stream held one of the server's
// threads with no bound, so that idle streams, which need no token, could starve the API. Here a
// stream costs no thread, is admitted by the StreamGuard (a bounded number, cancelled when idle)
// and answers from the process's generated descriptor pool.
#pragma once

#include <string>
#include <vector>

#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "server/streams.h"

namespace lsqsurf::server {

class ReflectionService final : public grpc::reflection::v1alpha::ServerReflection::CallbackService {
 public:
  // `services`: the full names of the services the server offers; `streams` must outlive it.
  ReflectionService(std::vector<std::string> services, StreamGuard& streams)
      : services_(std::move(services)), streams_(streams) {}
  static constexpr char kServiceName[] = "grpc.reflection.v1alpha.ServerReflection";

  grpc::ServerBidiReactor<grpc::reflection::v1alpha::ServerReflectionRequest,
                          grpc::reflection::v1alpha::ServerReflectionResponse>*
  ServerReflectionInfo(grpc::CallbackServerContext* context) override;

  // The answer to one request (also for tests).
  void Answer(const grpc::reflection::v1alpha::ServerReflectionRequest& request,
              grpc::reflection::v1alpha::ServerReflectionResponse* response) const;

 private:
  class Stream;
  const std::vector<std::string> services_;
  StreamGuard& streams_;
};

}  // namespace lsqsurf::server
