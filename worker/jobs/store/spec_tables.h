// worker/jobs/store/spec_tables.h — what a job store reads stored specs with.
#pragma once

#include <functional>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/params.h"

namespace lsqsurf::jobs {

// How the texts a store keeps become a spec again: a method's parameter table at its defaults
// (an error when this build has no such method) and the view options' table at its defaults.
// The store knows no job kind; the job layer gives the method registry's (RegistrySpecTables in
// method_registry.h).
struct SpecTables {
  std::function<absl::StatusOr<core::ParamSet>(std::string_view method)> params;
  std::function<core::ParamSet()> view;
};

}  // namespace lsqsurf::jobs
