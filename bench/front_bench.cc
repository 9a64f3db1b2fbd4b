// lsqsurf-front-bench — the front-tracking benchmarks of BENCHMARKS.md: Zalesak's slotted sphere
// (one revolution) and Enright's 3D deformation (t = T), with volume change, the E1 shape error
// against the exact initial shape, point counts, wall time and peak RSS.
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "worker/core/job_context.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/front/front_tracking.h"
#include "worker/jobs/pictures.h"
#include "worker/render/render.h"

namespace {

// Runs every point of the front at time t back to t = 0 (RK4, steps of dt/2) and measures how far
// it lands from the exact initial surface: mean and max. A point that lies on the true front at
// time t lands on the initial surface, so this is the front's error at t, free of any surface
// fit.
std::pair<double, double> PreimageError(const lsqsurf::front::VelocityField& field, const lsqsurf::front::Front& front,
                                        double t, double dt, lsqsurf::front::InitialShape shape) {
  using lsqsurf::core::Vec3d;
  const int steps = static_cast<int>(std::ceil(2 * t / dt - 1e-9));
  if (steps == 0) return {0.0, 0.0};
  const double back = -t / steps;
  std::vector<double> error(front.points.size());
  lsqsurf::core::LocalJobContext ctx;
  (void)lsqsurf::core::ParallelFor(
      front.points.size(), 256,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) {
          Vec3d x = front.points[i].cast<double>();
          for (int s = 0; s < steps; ++s) x = lsqsurf::front::Rk4Step(field, x, t + s * back, back);
          error[i] = std::abs(lsqsurf::front::ShapeValue(shape, x));
        }
      },
      &ctx);
  double sum = 0, max = 0;
  for (double d : error) sum += d, max = std::max(max, d);
  return {sum / static_cast<double>(error.size()), max};
}

// The frame's points themselves: a mesh extracted on cubes of edge h would drop sheets thinner
// than h that the front still carries.
absl::Status WriteFramePicture(lsqsurf::render::Renderer& renderer, const lsqsurf::front::Front& front,
                               const std::string& dir, int step) {
  lsqsurf::core::PointCloud cloud;
  cloud.positions = front.points;
  cloud.normals = front.normals;
  lsqsurf::render::RenderParams view;
  view.width = view.height = 768;
  view.camera.framing_box = lsqsurf::core::Box3(lsqsurf::core::Vec3d::Zero(), lsqsurf::core::Vec3d::Ones());
  return lsqsurf::jobs::WritePicture(renderer, cloud, view, dir + "/frame_" + std::to_string(step) + ".png");
}

// The time step and step count: as given, or one revolution with Δt = 1 (Zalesak), or about a
// cell per step at the field's peak speed up to t = T (Enright).
void SetSchedule(bool zalesak, double dt, int steps, int cells, double period, lsqsurf::front::TrackingParams& p) {
  if (zalesak) {
    p.dt = dt > 0 ? dt : 1.0;
    p.steps = steps > 0 ? steps : static_cast<int>(std::lround(628 / p.dt));
  } else {
    p.steps = steps > 0 ? steps : std::max(50, static_cast<int>(std::lround(150.0 * cells / 64)));
    p.dt = dt > 0 ? dt : period / p.steps;
  }
}

std::unique_ptr<lsqsurf::front::VelocityField> EnrightField(double period, const std::string& modulation) {
  using lsqsurf::front::TimeModulation;
  return lsqsurf::front::EnrightDeformation(
      period, modulation == "reversal" ? TimeModulation::kReversal : TimeModulation::kCosine);
}

}  // namespace

int main(int argc, char** argv) {
  using namespace lsqsurf;
  CLI::App app{"lsqsurf-front-bench: Zalesak and Enright front-tracking tests"};
  std::string test = "zalesak";
  int cells = 128;
  double dt = 0;
  int steps = 0;
  double period = 3.0;
  int stride = 0;
  std::string shape_name;
  bool mesh_check = false;
  std::string pictures;
  std::string resampling = "markers";
  bool preimage = false;
  front::TrackingParams p;  // The tracking options below fill it directly.
  app.add_option("--test", test, "zalesak | enright")->capture_default_str();
  app.add_option("--cells", cells, "grid cells per unit (h = 1/cells)")->capture_default_str();
  app.add_option("--dt", dt, "time step (default: 1 for zalesak, T/(150·cells/64) for enright)");
  app.add_option("--steps", steps, "steps (default: one revolution or t = T)");
  app.add_option("--period", period, "Enright period T")->capture_default_str();
  std::string modulation = "cos";
  app.add_option("--modulation", modulation,
                 "Enright field in time: cos (cos(pi t/T)) | reversal (+1 before T/2, -1 after, as the seed)")
      ->check(CLI::IsMember({"cos", "reversal"}))
      ->capture_default_str();
  app.add_option("--stride", stride, "print every this many steps (default: steps/8)");
  app.add_option("--support", p.support_factor, "RAMLS support radius in units of h")->capture_default_str();
  app.add_flag("--mesh-check", mesh_check, "also print each frame's mesh volume (cross-check of the gridline volume)");
  app.add_option("--pictures", pictures,
                 "write a picture of each printed frame's points as DIR/frame_STEP.png (the directory must exist)");
  app.add_option("--resampling", resampling, "gridlines (the seed's re-generation) | markers")->capture_default_str();
  app.add_option("--marker-spacing", p.marker_spacing, "markers: thinning distance in units of h")
      ->capture_default_str();
  app.add_option("--marker-gap", p.marker_gap, "markers: gap-filling distance in units of h")->capture_default_str();
  app.add_option("--merge-distance", p.merge_distance,
                 "fronts closer than this (units of h) merge and thinner necks pinch off; 0 = never")
      ->capture_default_str();
  app.add_flag("--preimage", preimage,
               "also print, for each printed frame, how far the points' preimages (the flow run back to t = 0) lie "
               "from the exact initial surface, in units of h: the front's true error at that time");
  app.add_option("--regeneration-stretch", p.regeneration_stretch,
                 "gridlines: re-generate once neighbouring points may have spread by this factor (1 = every step)")
      ->capture_default_str();
  app.add_option("--max-points", p.max_points, "stop when the front grows past this many points")
      ->capture_default_str();
  app.add_option("--shape", shape_name, "sphere | slotted (default: the test's own shape)");
  CLI11_PARSE(app, argc, argv);
  const bool zalesak = test == "zalesak";
  if (!zalesak && test != "enright") return std::fprintf(stderr, "unknown --test %s\n", test.c_str()), 2;
  p.h = 1.0 / cells;
  if (resampling != "gridlines" && resampling != "markers") return std::fprintf(stderr, "unknown --resampling\n"), 2;
  p.resampling = resampling == "markers" ? front::Resampling::kMarkers : front::Resampling::kGridlines;
  SetSchedule(zalesak, dt, steps, cells, period, p);
  p.output_stride = stride > 0 ? stride : std::max(1, p.steps / 8);
  if (shape_name.empty()) shape_name = zalesak ? "slotted" : "sphere";
  if (shape_name != "sphere" && shape_name != "slotted") return std::fprintf(stderr, "unknown --shape\n"), 2;
  const front::InitialShape shape =
      shape_name == "slotted" ? front::InitialShape::kZalesakSphere : front::InitialShape::kSphere;
  auto initial = front::SampleInitialFront(shape, p.h);
  if (!initial.ok()) return std::fprintf(stderr, "%s\n", initial.status().ToString().c_str()), 1;
  auto e1_initial = front::ShapeError(*initial, shape, p.h);
  if (!e1_initial.ok()) return std::fprintf(stderr, "%s\n", e1_initial.status().ToString().c_str()), 1;
  const auto field = zalesak ? front::ZalesakRotation() : EnrightField(period, modulation);
  std::printf("%s h=1/%d dt=%g steps=%d resampling=%s%s\n", test.c_str(), cells, p.dt, p.steps, resampling.c_str(),
              zalesak ? "" : (" T=" + std::to_string(period) + " modulation=" + modulation).c_str());
  std::printf("%6s %9s %9s %12s %12s %9s%s\n", "step", "time", "points", "volume", "change_%", "wall_s",
              mesh_check ? "  mesh_volume mesh_vs_grid_%" : "");
  if (preimage)
    std::printf(
        "        (preimage columns: mean and max distance of the points' preimages from the exact surface, in h)\n");
  std::unique_ptr<render::Renderer> renderer;
  if (!pictures.empty()) {
    auto created = render::CreateRenderer();
    if (!created.ok()) return std::fprintf(stderr, "%s\n", created.status().ToString().c_str()), 1;
    renderer = std::move(*created);
  }
  core::LocalJobContext ctx;
  front::Front last;
  double wall = 0, volume0 = 0, volume_end = 0;
  size_t peak_points = 0;
  const auto start = std::chrono::steady_clock::now();
  const absl::Status s =
      front::Track(*initial, *field, p, ctx, [&](const front::FrameStats& f, const front::Front& fr) {
        if (f.step == 0) volume0 = f.volume;
        volume_end = f.volume;
        wall += f.seconds;
        peak_points = std::max(peak_points, f.points);
        std::printf("%6d %9.3f %9zu %12.6e %12.4f %9.2f", f.step, f.time, f.points, f.volume, 100 * f.volume_change,
                    wall);
        if (mesh_check) {
          auto mesh = front::FrontMesh(fr, p.h, ctx, p.support_factor, p.merge_distance);
          if (!mesh.ok()) return mesh.status();
          const double mesh_volume = core::EnclosedVolume(*mesh);
          std::printf(" %12.6e %12.4f", mesh_volume, 100 * (mesh_volume - f.volume) / f.volume);
        }
        if (preimage) {
          const auto [mean, max] = PreimageError(*field, fr, f.time, p.dt, shape);
          std::printf("  preimage %.2e %.2e", mean / p.h, max / p.h);
        }
        std::printf("\n");
        std::fflush(stdout);
        if (renderer) LSQSURF_RETURN_IF_ERROR(WriteFramePicture(*renderer, fr, pictures, f.step));
        last = fr;
        return absl::OkStatus();
      });
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (!s.ok()) return std::fprintf(stderr, "%s\n", s.ToString().c_str()), 1;
  auto e1 = front::ShapeError(last, shape, p.h, p.support_factor, p.merge_distance);
  if (!e1.ok()) return std::fprintf(stderr, "%s\n", e1.status().ToString().c_str()), 1;
  struct rusage usage {};
  ::getrusage(RUSAGE_SELF, &usage);
  std::printf(
      "summary: volume_change=%.4f%% e1_rel=%.4f%% (initial sampling: %.4f%%) points_start=%zu "
      "points_end=%zu points_peak=%zu wall=%.1fs peak_rss=%.0fMiB\n",
      100 * (volume_end - volume0) / volume0, 100 * *e1 / volume0, 100 * *e1_initial / volume0, initial->points.size(),
      last.points.size(), peak_points, seconds, static_cast<double>(usage.ru_maxrss) / 1024.0);
  return 0;
}
