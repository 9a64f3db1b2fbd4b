// worker/jobs/store/spec_tables.h — what a job store reads stored specs with.
#pragma once

#include <functional>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/params.h"

namespace lsqsurf::jobs {

// How the texts a store keeps become a spec again: a method's parameter table at its defaults
// (an error when this build has no such method), the view options' table at its defaults, and
// the format they are of.
// The store knows no job kind; the job layer gives the method registry's (RegistrySpecTables in
// method_registry.h).
struct SpecTables {
  std::function<absl::StatusOr<core::ParamSet>(std::string_view method)> params;
  std::function<core::ParamSet()> view;
  // The spec format these tables read and write: a job is stored with it, and a store claims
  // only jobs of this format or an older one (0: the format of stores before formats were kept).
  int format = 0;
};

}  // namespace lsqsurf::jobs
