// worker/jobs/engines.h — the registry of surface methods the service offers.
//
// Turns a method name and a flat parameter map into calls of the engine libraries, and
// describes every parameter (default, range, meaning) so that the server can validate requests
// before accepting them and the client can list them. The only place that knows every engine.
#pragma once

#include <map>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::jobs {

struct ParameterSpec {
  std::string name;
  double default_value = 0;
  double min_value = 0;
  double max_value = 0;
  bool integer = false;
  std::string help;  // Meaning and units.
};

struct MethodSpec {
  std::string name;
  std::string description;
  std::vector<ParameterSpec> parameters;
  std::vector<std::string> attributes;  // Per-vertex scalars on its result meshes (to colour by).
};

using ParameterMap = std::map<std::string, double>;

// Every method, with its parameters (including the common `estimate_normals` and
// `normal_neighbors`).
const std::vector<MethodSpec>& SurfaceMethods();

// The method called `name`, or nullptr.
const MethodSpec* FindMethod(const std::string& name);

// kInvalidArgument for an unknown method (listing the known ones), an unknown parameter
// (listing the valid ones), a non-integer where an integer is needed, or a value out of range.
absl::Status ValidateRequest(const std::string& method, const ParameterMap& parameters);

// The value of `name`: the given one or the documented default.
double ParameterOrDefault(const std::string& method, const ParameterMap& parameters,
                          const std::string& name);

struct SurfaceResult {
  core::TriangleMesh mesh;
  std::vector<std::pair<std::string, double>> statistics;  // Name, value (units in the name).
};

// Runs a validated request on a cloud. Estimates normals first when the cloud has none and
// `estimate_normals` is 1. Errors: kInvalidArgument, kResourceExhausted, kCancelled, or the
// engine's own error.
absl::StatusOr<SurfaceResult> RunSurfaceMethod(const std::string& method,
                                               const ParameterMap& parameters,
                                               core::PointCloud cloud, core::JobContext& ctx);

}  // namespace lsqsurf::jobs
