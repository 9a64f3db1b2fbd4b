// lsqsurf-csg-bench — CSG and local edits of kept PU results against extracting one alone.
//
// Two clouds of one shared model (different samples, the second turned and shifted by a share of
// the model's size) are fitted with PU defaults; the first is extracted alone (the baseline),
// both functions go through their stored byte form, and the csg engine extracts their union and
// the first minus a sphere; a local edit (degree 1 in a ball holding 1 % of the points) is timed
// against the fit and extraction it replaces. Prints time, triangles, topology as delivered (merged by position)
// and the peak RSS of the whole run.
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "worker/core/mesh_metrics.h"
#include "worker/core/sampling.h"
#include "worker/core/strings.h"
#include "worker/csg/csg.h"
#include "worker/io/files.h"
#include "worker/jobs/csg_job.h"
#include "worker/pu/pu.h"

namespace {

using namespace lsqsurf;
using Clock = std::chrono::steady_clock;

double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

double PeakMiB() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;
}

void Report(const char* what, double seconds, const core::TriangleMesh& mesh) {
  const core::MeshTopology t = core::AnalyzeTopology(core::WeldByPosition(mesh));
  std::printf("%-28s %8.2f s %10zu triangles  boundary=%lld non-manifold=%lld comps=%lld  peak %.0f MiB\n", what,
              seconds, mesh.faces.size(), static_cast<long long>(t.boundary_edges),
              static_cast<long long>(t.non_manifold_edges), static_cast<long long>(t.components), PeakMiB());
}

absl::StatusOr<csg::Operand> AsOperand(const pu::PuFunction& function) {
  const auto start = Clock::now();
  const std::string bytes = pu::SerializePu(function);
  auto back = pu::DeserializePu(bytes);
  if (!back.ok()) return back.status();
  std::printf("%-28s %8.2f s %10.1f MiB stored\n", "store + load function", Since(start),
              static_cast<double>(bytes.size()) / (1 << 20));
  return jobs::MakePuOperand(*std::move(back));
}

// A local edit of a ball holding about 1 % of the points: the edit of the fits, the local
// re-extraction and, for comparison, the whole extraction of the edited function.
bool BenchLocalEdit(const pu::PuFunction& function, pu::KeptSurface kept, core::LocalJobContext& ctx) {
  // A local edit of a ball holding about 1 % of the points, against fitting and extracting anew.
  const core::Vec3f& p = function.points()[function.points().size() / 2];
  std::vector<float> d2;
  for (const core::Vec3f& q : function.points()) d2.push_back((q - p).squaredNorm());
  std::nth_element(d2.begin(), d2.begin() + static_cast<long>(d2.size() / 100), d2.end());
  pu::PuEdit edit;
  edit.centre = p.cast<double>();
  edit.radius = std::sqrt(static_cast<double>(d2[d2.size() / 100]));
  const auto start = Clock::now();
  pu::PuEditStats stats;
  auto edited = pu::EditPu(function, edit, ctx, &stats);
  if (!edited.ok()) {
    std::fprintf(stderr, "%s\n", edited.status().ToString().c_str());
    return false;
  }
  const double edit_seconds = Since(start);
  std::printf("%-28s %8.2f s (%lld fits replaced)\n", "edit 1 % ball: fits", edit_seconds,
              static_cast<long long>(stats.fits_replaced));
  const auto local_start = Clock::now();
  auto local = pu::ExtractEdited(function, **edited, stats, std::move(kept), pu::PuExtractParams{}, ctx);
  if (!local.ok()) {
    std::fprintf(stderr, "%s\n", local.status().ToString().c_str());
    return false;
  }
  std::printf("%-28s %8.2f s (%lld faces replaced, %lld seam edges)\n", "edit 1 % ball: local extract",
              Since(local_start), static_cast<long long>(local->stats.replaced_faces),
              static_cast<long long>(local->stats.seam_edges));
  Report("edit 1 % ball: fits + local", Since(start), local->mesh);
  const auto whole_start = Clock::now();
  auto whole = pu::Extract(**edited, pu::PuExtractParams{}, ctx);
  if (!whole.ok()) return false;
  Report("edit 1 % ball: whole extract", Since(whole_start), whole->mesh);
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"CSG of kept PU results against extracting one alone"};
  std::string data_dir = "../shared/data/meshes", model = "spot";
  size_t points = 1'000'000;
  double shift = 0.3, turn = 0;
  double crease_angle = csg::CsgParams{}.marching.crease_angle;
  int relax_steps = csg::CsgParams{}.marching.relax_steps;
  app.add_option("--data", data_dir, "folder with <model>.obj")->capture_default_str();
  app.add_option("--model", model, "model name")->capture_default_str();
  app.add_option("--points", points, "points per cloud")->capture_default_str();
  app.add_option("--shift", shift, "second operand's shift, share of the model's largest side")->capture_default_str();
  app.add_option("--turn", turn, "second operand's turn about y, degrees")->capture_default_str();
  app.add_option("--crease-angle", crease_angle, "csg crease_angle")->capture_default_str();
  app.add_option("--relax-steps", relax_steps, "csg relax_steps")->capture_default_str();
  bool edit_only = false;
  app.add_flag("--edit-only", edit_only, "time the local edit only, not the CSG cases");
  CLI11_PARSE(app, argc, argv);

  auto truth = io::ReadMeshFile((std::filesystem::path(data_dir) / (model + ".obj")).string());
  if (!truth.ok()) {
    std::fprintf(stderr, "%s\n", truth.status().ToString().c_str());
    return 1;
  }
  const core::Box3 box = core::BoundingBox(truth->vertices);
  const double side = box.sizes().maxCoeff();
  core::LocalJobContext ctx;
  std::vector<std::unique_ptr<pu::PuFunction>> fitted;
  double fit_seconds = 0;
  for (uint64_t seed : {1234u, 4321u}) {
    if (edit_only && !fitted.empty()) break;
    const auto start = Clock::now();
    auto f = pu::BuildPu(core::SampleCloud(*truth, points, seed), pu::PuParams{}, ctx);
    if (!f.ok()) {
      std::fprintf(stderr, "%s\n", f.status().ToString().c_str());
      return 1;
    }
    std::printf("%-28s %8.2f s\n", core::StrCat("fit ", points, " points").c_str(), Since(start));
    if (fitted.empty()) fit_seconds = Since(start);
    fitted.push_back(*std::move(f));
  }
  pu::KeptSurface kept;
  {
    const auto start = Clock::now();
    pu::PuExtractParams traced;
    traced.marching.trace = true;  // As the service extracts what it keeps.
    auto alone = pu::Extract(*fitted[0], traced, ctx);
    if (!alone.ok()) return 1;
    const double seconds = Since(start);
    Report("extract one alone (pu)", seconds, alone->mesh);
    std::printf("%-28s %8.2f s\n", "fit + extract (recompute)", fit_seconds + seconds);
    std::printf("%-28s %8.1f MiB\n", "kept surface (traced)",
                static_cast<double>(pu::SerializeSurface(alone->mesh, alone->trace, traced).size()) / (1 << 20));
    kept = {std::move(alone->mesh), std::move(alone->trace), traced};
  }
  if (!BenchLocalEdit(*fitted[0], std::move(kept), ctx)) return 1;
  if (edit_only) return 0;
  std::vector<csg::Operand> operands;
  for (const auto& f : fitted) {
    auto operand = AsOperand(*f);
    if (!operand.ok()) {
      std::fprintf(stderr, "%s\n", operand.status().ToString().c_str());
      return 1;
    }
    operands.push_back(*std::move(operand));
  }
  fitted.clear();
  const auto resolve = [&](const std::string& id) -> absl::StatusOr<csg::Operand> {
    return operands[id == "a" ? 0 : 1];
  };
  const core::Vec3d c = box.center();
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"union(a, turned+shifted b)", core::StrCat("union(job:a rotate(axis=0,1,0 deg=", turn, " c=", c.x(), ",", c.y(),
                                                  ",", c.z(), " translate(t=", shift * side, ",0,0 job:b)))")},
      {"a minus sphere", core::StrCat("difference(job:a sphere(c=", c.x() + 0.3 * side, ",", c.y(), ",", c.z(),
                                      " r=", 0.25 * side, "))")},
  };
  for (const auto& [name, text] : cases) {
    auto root = csg::ParseCsg(text);
    if (!root.ok()) return 1;
    const auto start = Clock::now();
    auto function = csg::BuildCsg(*root, resolve);
    if (!function.ok()) {
      std::fprintf(stderr, "%s\n", function.status().ToString().c_str());
      return 1;
    }
    csg::CsgStats stats;
    csg::CsgParams params;
    params.marching.crease_angle = crease_angle;
    params.marching.relax_steps = relax_steps;
    auto mesh = csg::ExtractCsg(**function, params, ctx, &stats);
    if (!mesh.ok()) {
      std::fprintf(stderr, "%s\n", mesh.status().ToString().c_str());
      return 1;
    }
    Report(name.c_str(), Since(start), mesh->mesh);
  }
  return 0;
}
