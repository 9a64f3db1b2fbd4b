#include "worker/jobs/edit_job.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <functional>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/jobs/shared_extraction.h"
#include "worker/jobs/surface_job.h"

namespace lsqsurf::jobs {
namespace {

const core::ParamTable<EditJobParams>& EditJobParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<EditJobParams>();
    t->Text<&EditJobParams::source>("source", "id of a succeeded pu or edit job with a kept function (required)")
        .Include(&EditJobParams::edit, pu::PuEditParamTable())
        .Include(&EditJobParams::extract, pu::PuExtractParamTable())
        .AddRule([](const EditJobParams& p) {
          return p.source.empty() ? absl::InvalidArgumentError("name the job to edit (source=ID)") : absl::OkStatus();
        });
    return t;
  }();
  return *table;
}

// The edited surface from the source's kept one, re-extracted only near the edit.
// kFailedPrecondition where that cannot be done (nothing kept, other parameters, no exact join).
absl::StatusOr<extract::IsosurfaceResult> ExtractNearEdit(const pu::PuFunction& before, const pu::PuFunction& after,
                                                          const pu::PuEditStats& edit_stats,
                                                          const pu::PuExtractParams& params, const std::string& source,
                                                          RunEnvironment& env, core::JobContext& ctx) {
  auto stored = ReadKeptArtifact(env, source, kPuSurfaceArtifact);
  if (!stored.ok()) return stored.status();
  auto kept = pu::DeserializeSurface(*stored);
  stored->clear();
  if (!kept.ok()) return absl::FailedPreconditionError(kept.status().message());
  return pu::ExtractEdited(before, after, edit_stats, *std::move(kept), params, ctx);
}

class EditKind final : public TypedJobKind<EditJobParams, NoInput> {
 public:
  std::string_view name() const override { return "edit"; }

  std::vector<MethodInfo> Methods() const override {
    return {{"edit",
             "Local edit of a kept PU function in a ball (set the degree, refit finer, or remove), and the edited "
             "surface as a new result",
             core::ParamSet(EditJobParamTable()),
             {"depth", "degree", "feature"},
             {}}};
  }

  // No upload slots are listed, so the job service refuses any upload before this.
  absl::StatusOr<Checked> Decode(const JobSpec&, const EditJobParams&, const Uploads&,
                                 const InputLimits&) const override {
    return Checked{};
  }

  std::vector<std::string> Referenced(const EditJobParams& p) const override { return {p.source}; }

  absl::StatusOr<Statistics> RunDecoded(const JobSpec& spec, const EditJobParams& params, NoInput,
                                        RunEnvironment& env) const override {
    const EditJobParams* p = &params;
    Statistics stats;
    auto stat = [&](std::string name, double value) { stats.emplace_back(std::move(name), value); };
    auto start = std::chrono::steady_clock::now();
    env.context.ReportProgress("reading the function", 0.0);
    auto base = ReadKeptPuFunction(env, p->source);
    if (!base.ok())
      return absl::Status(base.status().code(), core::StrCat("source job ", p->source, ": ", base.status().message()));
    stat("load_seconds", core::SecondsSince(start));
    start = std::chrono::steady_clock::now();
    const pu::PuEdit& edit = p->edit;
    pu::PuEditStats edit_stats;
    core::SubContext edit_ctx(env.context, "editing the fits", 0.05, 0.2);
    auto edited = pu::EditPu(**base, edit, edit_ctx, &edit_stats);
    if (!edited.ok()) return edited.status();
    stat("edit_seconds", core::SecondsSince(start));
    stat("fits_replaced", static_cast<double>(edit_stats.fits_replaced));
    stat("fits_after", static_cast<double>(edit_stats.fits_after));
    stat("points_removed", static_cast<double>(edit_stats.points_removed));
    stat("edit_reach", edit_stats.reach);
    start = std::chrono::steady_clock::now();
    core::SubContext extract_ctx(env.context, "extracting surface", 0.2, 0.95);
    pu::PuExtractParams extract = p->extract;
    extract.marching.trace = true;
    extract.max_leaves = LeavesWithin(env.memory_bytes, extract.max_leaves);
    auto extracted = ExtractNearEdit(**base, **edited, edit_stats, extract, p->source, env, extract_ctx);
    base->reset();
    const bool local = extracted.ok();
    if (!local) {
      if (extracted.status().code() != absl::StatusCode::kFailedPrecondition) return extracted.status();
      spdlog::info("edit of {}: the whole surface is extracted ({})", p->source, extracted.status().message());
      extracted = pu::Extract(**edited, extract, extract_ctx);
      if (!extracted.ok()) return extracted.status();
    }
    stat("extract_seconds", core::SecondsSince(start));
    stat("local_extraction", local ? 1 : 0);
    stat("replaced_faces", static_cast<double>(extracted->stats.replaced_faces));
    stat("seam_edges", static_cast<double>(extracted->stats.seam_edges));
    // The next edit joins onto the surface as marched; the one delivered has its small holes
    // closed, except the one a removal cut.
    std::string kept_surface = pu::SerializeSurface(extracted->mesh, extracted->trace, extract);
    std::function<bool(const core::Vec3f&)> cut_here;
    if (edit.action == pu::PuEditAction::kRemove) {
      cut_here = [&](const core::Vec3f& v) {
        return std::ranges::any_of(edit_stats.changed, [&](const pu::PuEditStats::Ball& b) {
          return (v.cast<double>() - b.centre).norm() <= b.radius;
        });
      };
    }
    extract::CloseSmallHoles(*extracted, kClosedHoleEdges, cut_here);
    if (extracted->stats.filled_holes > 0) stat("filled_holes", static_cast<double>(extracted->stats.filled_holes));
    AddMeshStatistics(extracted->mesh, extracted->stats, &stats);
    LSQSURF_RETURN_IF_ERROR(DeliverMesh(extracted->mesh, spec, env, &stats));
    LSQSURF_RETURN_IF_ERROR(env.sink.Write(kPuFunctionArtifact, pu::SerializePu(**edited)));
    LSQSURF_RETURN_IF_ERROR(env.sink.Write(kPuSurfaceArtifact, std::move(kept_surface)));
    return stats;
  }
};

}  // namespace

const JobKind& EditJobKind() {
  static const EditKind kind;
  return kind;
}

}  // namespace lsqsurf::jobs
