// server/convert.h — the one place where job-layer and renderer types meet protobuf and gRPC.
#pragma once

#include <grpcpp/support/status.h>

#include "absl/status/statusor.h"
#include "lsqsurf/v1/reconstruction.pb.h"
#include "worker/jobs/job.h"
#include "worker/render/render.h"

namespace lsqsurf::server {

// abseil and gRPC share the canonical code numbering; the message passes through unchanged.
grpc::Status ToGrpcStatus(const absl::Status& status);

void ToProto(const jobs::JobRecord& record, v1::Job* out);
// Errors: kInvalidArgument for a field that cannot be represented (an unknown up axis).
absl::StatusOr<jobs::JobSpec> FromProto(const v1::JobSpec& spec);
// Unset fields (0, empty, absent optionals) keep the RenderParams defaults; ranges are not
// checked here (render::Validate does). Errors: kInvalidArgument (an unknown up axis).
absl::StatusOr<render::RenderParams> FromProto(const v1::RenderOptions& options);
void ToProto(const render::RenderParams& params, v1::RenderOptions* out);

}  // namespace lsqsurf::server
