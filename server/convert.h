// server/convert.h — the one place where job-layer and renderer types meet protobuf and gRPC.
#pragma once

#include <grpcpp/support/status.h>

#include "absl/status/status.h"
#include "lsqsurf/v1/reconstruction.pb.h"
#include "worker/jobs/job.h"
#include "worker/render/render.h"

namespace lsqsurf::server {

// abseil and gRPC share the canonical code numbering; the message passes through unchanged.
grpc::Status ToGrpcStatus(const absl::Status& status);

void ToProto(const jobs::JobRecord& record, v1::Job* out);
jobs::JobSpec FromProto(const v1::JobSpec& spec);
// Unset fields (0, empty, absent optionals) keep the RenderParams defaults; not validated here.
render::RenderParams FromProto(const v1::RenderRequest& request);

}  // namespace lsqsurf::server
