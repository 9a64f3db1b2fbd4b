#include "worker/jobs/csg_job.h"

#include <chrono>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/jobs/surface_job.h"
#include "worker/pu/pu.h"

namespace lsqsurf::jobs {
namespace {

const core::ParamTable<csg::CsgParams>& CsgExtractTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<csg::CsgParams>();
    t->Real<&csg::CsgParams::cell_size>("cell_size", 0, 1e12, "model units",
                                        "edge of the finest extraction cells at the surface; 0 = the finest of the "
                                        "referenced jobs' own, or 1/256 of the solid's longest side")
        .Include(&csg::CsgParams::marching, extract::MarchingParamTable());
    return t;
  }();
  return *table;
}

const core::ParamTable<CsgJobParams>& CsgJobParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<CsgJobParams>();
    t->Text<&CsgJobParams::expression>(
         "expression",
         "the solid, e.g. difference(job:ID, sphere(c=0.1,0.2,0.3 r=0.05)): union, intersection, difference of "
         "sphere, box, cylinder, torus, plane, translate, rotate, scale and job:ID (a succeeded pu job); see the "
         "README (required)")
        .Include(&CsgJobParams::extract, CsgExtractTable())
        .AddRule([](const CsgJobParams& p) {
          if (p.expression.empty()) return absl::InvalidArgumentError("give the solid as expression=...");
          return csg::ParseCsg(p.expression).status();
        });
    return t;
  }();
  return *table;
}

// The extraction's parameters with its leaves bounded by the job's memory.
csg::CsgParams Bounded(csg::CsgParams params, int64_t memory_bytes) {
  params.max_leaves = LeavesWithin(memory_bytes, params.max_leaves);
  return params;
}

class CsgKind final : public TypedJobKind<CsgJobParams, NoInput> {
 public:
  std::string_view name() const override { return "csg"; }

  std::vector<MethodInfo> Methods() const override {
    return {{"csg",
             "Boolean combination (union, intersection, difference) of analytic primitives and kept PU results, "
             "extracted as one closed mesh with crisp intersection curves",
             core::ParamSet(CsgJobParamTable()),
             {"operand"},
             {}}};
  }

  // No upload slots are listed, so the job service refuses any upload before this. A solid of
  // primitives alone is built here, so that one that is unbounded, too large, or would need more
  // cells than the extraction allows is refused now rather than failing (or growing) later;
  // with job references that waits for the run, which checks the same before it extracts.
  absl::StatusOr<Checked> Decode(const JobSpec&, const CsgJobParams& params, const Uploads&,
                                 const InputLimits& limits) const override {
    const CsgJobParams* p = &params;
    LSQSURF_ASSIGN_OR_RETURN(csg::CsgNode root, csg::ParseCsg(p->expression));
    if (!csg::ReferencedJobs(root).empty()) return Checked{};
    LSQSURF_ASSIGN_OR_RETURN(auto function, csg::BuildCsg(root, [](const std::string&) -> absl::StatusOr<csg::Operand> {
                               return absl::InternalError("no job references here");
                             }));
    LSQSURF_RETURN_IF_ERROR(csg::CheckExtractionSize(*function, Bounded(p->extract, limits.max_job_memory)));
    return Checked{};
  }

  std::vector<std::string> Referenced(const CsgJobParams& p) const override {
    auto root = csg::ParseCsg(p.expression);
    return root.ok() ? csg::ReferencedJobs(*root) : std::vector<std::string>{};
  }

  absl::StatusOr<Statistics> RunDecoded(const JobSpec& spec, const CsgJobParams& params, NoInput,
                                        RunEnvironment& env) const override {
    const CsgJobParams* p = &params;
    LSQSURF_ASSIGN_OR_RETURN(csg::CsgNode root, csg::ParseCsg(p->expression));
    Statistics stats;
    auto stat = [&](std::string name, double value) { stats.emplace_back(std::move(name), value); };
    const auto load_start = std::chrono::steady_clock::now();
    env.context.ReportProgress("reading the operands", 0.0);
    auto function = csg::BuildCsg(root, [&](const std::string& id) -> absl::StatusOr<csg::Operand> {
      auto kept = ReadKeptPuFunction(env, id);
      if (!kept.ok()) return kept.status();
      return MakePuOperand(*std::move(kept));
    });
    if (!function.ok()) return function.status();
    stat("operands", (*function)->operand_count());
    stat("jobs_referenced", static_cast<double>(csg::ReferencedJobs(root).size()));
    stat("load_seconds", core::SecondsSince(load_start));
    const auto extract_start = std::chrono::steady_clock::now();
    core::SubContext extract_ctx(env.context, "extracting the solid", 0.1, 0.97);
    csg::CsgStats csg_stats;
    auto extracted = csg::ExtractCsg(**function, Bounded(p->extract, env.memory_bytes), extract_ctx, &csg_stats);
    if (!extracted.ok()) return extracted.status();
    LSQSURF_RETURN_IF_ERROR(env.context.CheckCancelled());  // Before measuring the whole mesh.
    stat("extract_seconds", core::SecondsSince(extract_start));
    stat("cell_size", csg_stats.cell_size);
    stat("seeds", static_cast<double>(csg_stats.seeds));
    stat("crease_vertices", static_cast<double>(extracted->stats.crease_vertices));
    stat("crease_corners", static_cast<double>(extracted->stats.crease_corners));
    stat("relaxed_vertices", static_cast<double>(extracted->stats.relaxed_vertices));
    stat("flipped_edges", static_cast<double>(extracted->stats.flipped_edges));
    AddMeshStatistics(extracted->mesh, extracted->stats, &stats);
    LSQSURF_RETURN_IF_ERROR(DeliverMesh(extracted->mesh, spec, env, &stats));
    return stats;
  }
};

}  // namespace

csg::Operand MakePuOperand(std::shared_ptr<const pu::PuFunction> function) {
  csg::Operand operand;
  const std::span<const core::Vec3f> points = function->points();
  operand.surface_points.assign(points.begin(), points.end());
  operand.bounds = core::BoundingBox(points);
  operand.cell_size = pu::FinestExtractionCell(*function, pu::PuExtractParams{});
  // Only its creases: the csg extraction measures the curvature of the combined surface itself.
  operand.near_crease = [function](const core::Vec3d& x) { return function->NearCrease(x); };
  operand.value = [function](const core::Vec3d& x, bool gradient) { return function->ValueOrDataSide(x, gradient); };
  return operand;
}

const JobKind& CsgJobKind() {
  static const CsgKind kind;
  return kind;
}

}  // namespace lsqsurf::jobs
