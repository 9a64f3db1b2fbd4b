// server/convert.h — the one place where job-layer types meet protobuf and gRPC.
//
// Parameters and view options are converted by name through protobuf reflection against the
// descriptor tables (worker/core/params.h): a proto field `foo` sets the table field `foo`,
// an enum value `PREFIX_BAR` the choice `bar`, and `PREFIX_UNSPECIFIED` leaves the default. No
// field is copied by hand, so the wire and the engines cannot drift apart silently; the
// server's tests check that every table field has its proto field and back.
#pragma once

#include <google/protobuf/message.h>
#include <grpcpp/support/status.h>

#include "absl/status/statusor.h"
#include "lsqsurf/v1/reconstruction.pb.h"
#include "worker/core/params.h"
#include "worker/jobs/job.h"

namespace lsqsurf::server {

// abseil and gRPC share the canonical code numbering; the message passes through unchanged.
grpc::Status ToGrpcStatus(const absl::Status& status);

// Applies the fields set in `message` to `params`. Errors: kInvalidArgument naming a field that
// is not a parameter here (e.g. `beta` for ramls), or a value out of range.
absl::Status FillParams(const google::protobuf::Message& message, core::ParamSet* params);
// Sets every field of `message` that `params` describes, to the current values.
void ParamsToProto(const core::ParamSet& params, google::protobuf::Message* message);

// A spec checked as the job service checks it (jobs::ValidateSpec). Errors: kInvalidArgument
// (no method set, a bad parameter, a broken cross-field rule, a bad view option).
absl::StatusOr<jobs::JobSpec> FromProto(const v1::JobSpec& spec);
// View options over the defaults. Errors: kInvalidArgument.
absl::StatusOr<core::ParamSet> FromProto(const v1::RenderOptions& options);

void ToProto(const jobs::JobRecord& record, v1::Job* out);
void ToProto(const core::ParamInfo& info, v1::Parameter* out);
v1::JobState ToProto(jobs::JobState state);

}  // namespace lsqsurf::server
