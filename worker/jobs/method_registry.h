// worker/jobs/method_registry.h — every method of every job kind, and the one validation of a
// job spec at the service boundary.
#pragma once

#include <cstdint>
#include <iterator>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/params.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/store/spec_tables.h"

namespace lsqsurf::jobs {

struct MethodEntry {
  MethodInfo info;
  const JobKind* kind = nullptr;
};

// Surface methods first, then front tracking. Built once; safe to read from any thread.
const std::vector<MethodEntry>& Methods();
// The method called `name`, or nullptr.
const MethodEntry* FindMethod(std::string_view name);
// The parameters of `method` at their defaults. Errors: kInvalidArgument for an unknown method,
// listing the known ones.
absl::StatusOr<core::ParamSet> DefaultParams(std::string_view method);
// View options (render::RenderParams) at their defaults: what previews and pictures take.
core::ParamSet DefaultView();
// A hash of every method's name with its parameters' names and types, and of the view options':
// what changes when a spec written by this build may not read whole in another.
uint64_t SpecFingerprint();

// Each spec format with the fingerprint of the tables it had. A change to the methods' tables
// appends the next format with the new fingerprint (tables_test holds the last one to this
// build's), so that servers of an older build leave the jobs of a newer one alone.
struct SpecFormat {
  int format;
  uint64_t fingerprint;
};
// 2: PU's threshold_spacings.
// 3: viewpoint, point_attributes and remove_outliers, for every surface method.
// 4: fill_holes, for every surface method.
// 5: undo_depth_steps, for every surface method.
inline constexpr SpecFormat kSpecFormats[] = {{1, 0x8c12ce01196d0c16},
                                              {2, 0x81bc4845708e1243},
                                              {3, 0x3149fd7d771d4a39},
                                              {4, 0x85c322b84911ba35},
                                              {5, 0x6098595d2e8444f9}};
// This build's spec format: what its stores write and claim up to (SpecTables::format).
inline constexpr int kSpecFormat = kSpecFormats[std::size(kSpecFormats) - 1].format;

// DefaultParams, DefaultView and kSpecFormat, for a job store to read stored specs with.
SpecTables RegistrySpecTables();

// The parameter reference of every method and of the view options, as Markdown: what
// docs/parameters.md holds (`lsqsurfd --parameter-reference` prints it).
std::string ParameterReference();

// Everything about a spec that can be checked without its uploads: a known method, parameters
// in range and consistent, the Draco bits, the preview's view and colour attribute (one the
// method's meshes carry). Errors: kInvalidArgument naming the field and what is accepted.
absl::Status ValidateSpec(const JobSpec& spec);

}  // namespace lsqsurf::jobs
