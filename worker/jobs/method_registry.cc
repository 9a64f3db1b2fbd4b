#include "worker/jobs/method_registry.h"

#include <cmath>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/jobs/csg_job.h"
#include "worker/jobs/edit_job.h"
#include "worker/jobs/probe_job.h"
#include "worker/jobs/surface_job.h"
#include "worker/jobs/track_job.h"
#include "worker/jobs/volume_job.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {

const std::vector<MethodEntry>& Methods() {
  static const auto* methods = [] {
    auto* out = new std::vector<MethodEntry>();
    for (const JobKind* kind :
         {&SurfaceJobKind(), &CsgJobKind(), &EditJobKind(), &TrackJobKind(), &VolumeJobKind(), &ProbeJobKind()}) {
      for (MethodInfo& info : kind->Methods()) out->push_back({std::move(info), kind});
    }
    return out;
  }();
  return *methods;
}

const MethodEntry* FindMethod(std::string_view name) {
  for (const auto& m : Methods()) {
    if (m.info.name == name) return &m;
  }
  return nullptr;
}

absl::StatusOr<core::ParamSet> DefaultParams(std::string_view method) {
  if (const MethodEntry* m = FindMethod(method)) return m->info.defaults;
  std::string known;
  for (const auto& m : Methods()) core::StrAppend(&known, known.empty() ? "" : ", ", m.info.name);
  return absl::InvalidArgumentError(core::StrCat("unknown method '", method, "'; available: ", known));
}

core::ParamSet DefaultView() { return core::ParamSet(render::ViewParamTable()); }

SpecTables RegistrySpecTables() { return {DefaultParams, DefaultView, kSpecFormat}; }

uint64_t SpecFingerprint() {
  // FNV-1a over "method|name:type;..." for every method, then the view options.
  uint64_t hash = 14695981039346656037ull;
  const auto add = [&hash](std::string_view text) {
    for (const char c : text) hash = (hash ^ static_cast<unsigned char>(c)) * 1099511628211ull;
  };
  const auto add_table = [&add](std::string_view owner, const core::ParamSet& table) {
    add(owner);
    add("|");
    for (const core::ParamInfo& info : table.Describe()) {
      add(info.name);
      add(core::StrCat(":", static_cast<int>(info.type), ";"));
    }
  };
  for (const auto& m : Methods()) add_table(m.info.name, m.info.defaults);
  add_table("view", DefaultView());
  return hash;
}

std::string ParameterReference() {
  std::string out =
      "# Parameter reference\n\n"
      "Generated from the engines' descriptor tables by `lsqsurfd --parameter-reference`; do not edit.\n"
      "On the command line: `lsqsurf reconstruct CLOUD --method METHOD --param NAME=VALUE`; in the API: the\n"
      "field NAME of the method's message in `JobSpec` (unset fields keep these defaults). Flags take\n"
      "true/false or 1/0, choices their names.\n";
  for (const auto& m : Methods()) {
    core::StrAppend(&out, "\n## ", m.info.name, "\n\n", m.info.description, "\n\n",
                    core::ParamReferenceMarkdown(m.info.defaults.Describe()));
    if (!m.info.attributes.empty()) {
      std::string names;
      for (const auto& a : m.info.attributes) core::StrAppend(&names, names.empty() ? "" : ", ", "`", a, "`");
      core::StrAppend(&out, "\nPer-vertex attributes of its meshes (to colour pictures by): ", names, ".\n");
    }
  }
  core::StrAppend(&out,
                  "\n## View options\n\nPictures (`lsqsurf render`, `--preview`, `--job-preview`, `track --pictures`;\n"
                  "`RenderOptions` in the API).\n\n",
                  core::ParamReferenceMarkdown(DefaultView().Describe()));
  return out;
}

absl::Status ValidateSpec(const JobSpec& spec) {
  const MethodEntry* m = FindMethod(spec.method);
  if (m == nullptr) return DefaultParams(spec.method).status();
  if (!spec.params.SameType(m->info.defaults)) {
    return absl::InternalError(core::StrCat("the parameters are not those of method ", spec.method));
  }
  if (absl::Status s = spec.params.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(core::StrCat(spec.method, ": ", s.message()));
  }
  if (spec.mesh_position_bits != 0 && (spec.mesh_position_bits < 8 || spec.mesh_position_bits > 30)) {
    return absl::InvalidArgumentError(
        core::StrCat("mesh_position_bits=", spec.mesh_position_bits, " must be 0 (chosen per mesh) or within [8, 30]"));
  }
  const PreviewSpec& preview = spec.preview;
  if (!preview.enabled) return absl::OkStatus();
  const auto* view = preview.view.As<render::RenderParams>();
  if (view == nullptr) return absl::InternalError("preview without view options");
  if (absl::Status s = render::Validate(*view); !s.ok()) {
    return absl::InvalidArgumentError(core::StrCat("preview: ", s.message()));
  }
  if (!(std::abs(preview.turntable_deg_per_frame) <= 360)) {
    return absl::InvalidArgumentError("preview: turntable_deg_per_frame must be within [-360, 360]");
  }
  const std::string& colour = view->color_attribute;
  if (colour.empty()) return absl::OkStatus();
  std::string known;
  for (const std::string& a : m->info.attributes) {
    if (a == colour) return absl::OkStatus();
    core::StrAppend(&known, known.empty() ? "" : ", ", a);
  }
  return absl::InvalidArgumentError(core::StrCat("preview: the ", spec.method, " method's results have no attribute '",
                                                 colour,
                                                 "' to colour by; they have: ", known.empty() ? "none" : known));
}

}  // namespace lsqsurf::jobs
