#include "worker/front/front_tracking.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/front/front_internal.h"

namespace lsqsurf::front {

const core::ParamTable<TrackingParams>& TrackingParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<TrackingParams>();
    t->Real<&TrackingParams::h>("h", 1.0 / 512, 1.0 / 8, "unit-cube lengths",
                                "background grid spacing; 1/h must be whole")
        .Real<&TrackingParams::dt>("dt", 1e-6, 1000, "time units", "time step")
        .Integer<&TrackingParams::steps>("steps", 1, 100000, "", "number of steps")
        .Integer<&TrackingParams::output_stride>("stride", 1, 100000, "steps",
                                                 "write a frame every this many steps (and after the last)")
        .Real<&TrackingParams::support_factor>("support_factor", 1.5, 10, "h", "RAMLS support radius")
        .Choice<&TrackingParams::resampling>(
            "resampling",
            {{"markers", static_cast<int>(Resampling::kMarkers),
              "the advected points stay; crowded ones are thinned, stretched gaps filled from the RAMLS surface of "
              "their side; keeps sheets thinner than h"},
             {"gridlines", static_cast<int>(Resampling::kGridlines),
              "the seed's re-generation of the whole front on the gridlines (see regeneration_stretch)"}},
            "how the front stays sampled after each step")
        .Real<&TrackingParams::marker_spacing>("marker_spacing", 0.1, 1, "h",
                                               "markers: of two markers facing the same way closer than this, the "
                                               "younger goes")
        .Real<&TrackingParams::marker_gap>("marker_gap", 0.15, 1, "h",
                                           "markers: a midpoint of two markers with no marker within this gets a "
                                           "new one; must exceed marker_spacing")
        .Real<&TrackingParams::merge_distance>("merge_distance", 0, 5, "h",
                                               "fronts closer than this merge and necks thinner than it pinch off; at "
                                               "most support_factor/2; 1.25-1.5 with the default support; 0 keeps "
                                               "every thin sheet and gap")
        .Real<&TrackingParams::regeneration_stretch>(
            "regeneration_stretch", 1, 4, "",
            "gridlines: re-generate the front once the flow may have spread neighbouring points by this factor; 1 = "
            "every step (the seed's literal scheme)")
        .Integer<&TrackingParams::max_points>("max_points", 100, 50'000'000, "points",
                                              "stop with an error if the front grows past this many points")
        .AddRule([](const TrackingParams& p) { return ValidateSpacing(p.h); })
        .AddRule([](const TrackingParams& p) {
          // The blend compares the two sides' fits over 2·merge_distance·h; only the support
          // sees both, so a wider blend would switch on and off at the support's edge.
          return 2 * p.merge_distance <= p.support_factor + 1e-12
                     ? absl::OkStatus()
                     : absl::InvalidArgumentError(
                           core::StrCat("merge_distance=", p.merge_distance,
                                        " may be at most half of support_factor=", p.support_factor));
        })
        .AddRule([](const TrackingParams& p) {
          return p.marker_gap > p.marker_spacing
                     ? absl::OkStatus()
                     : absl::InvalidArgumentError(
                           core::StrCat("marker_gap=", p.marker_gap, " must exceed marker_spacing=", p.marker_spacing));
        });
    return t;
  }();
  return *table;
}

absl::Status Validate(const TrackingParams& p) { return TrackingParamTable().Validate(p); }

absl::Status Track(const Front& initial, const VelocityField& velocity, const TrackingParams& params,
                   core::JobContext& ctx,
                   const std::function<absl::Status(const FrameStats&, const Front&)>& on_frame) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (initial.points.size() < 4 || initial.normals.size() != initial.points.size()) {
    return absl::InvalidArgumentError("the initial front needs at least 4 points, each with a normal");
  }
  const double h = params.h, dt = params.dt;
  std::vector<bool> marks;
  Markers markers{initial, std::vector<int>(initial.points.size(), 0)};
  Front& front = markers.front;
  auto z0 = ZCrossings(front, h, h, params.support_factor, params.merge_distance, marks, ctx);
  if (!z0.ok()) return z0.status();
  const double v0 = VolumeOf(*z0, h);
  if (!(v0 > 0))
    return absl::InvalidArgumentError(
        "the initial front encloses no volume on the grid; is it closed and oriented outward?");
  FrameStats stats;
  stats.points = front.points.size();
  stats.volume = v0;
  LSQSURF_RETURN_IF_ERROR(on_frame(stats, front));
  auto since = std::chrono::steady_clock::now();
  const bool gridlines = params.resampling == Resampling::kGridlines;
  double log_stretch = 0;  // ∫ λ dt since the last re-generation (gridlines).
  for (int step = 1; step <= params.steps; ++step) {
    const double t = (step - 1) * dt;
    // 1. Advection (RK4) and normal transport; in the gridline mode also the largest strain rate.
    std::atomic<bool> finite{true};
    std::atomic<double> strain_rate{0};
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        front.points.size(), 512,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i) {
            const Vec3d p = front.points[i].cast<double>();
            const Vec3d moved = Rk4Step(velocity, p, t, dt);
            const Vec3d n = front.normals[i].cast<double>();
            const Eigen::Matrix3d jacobian = Jacobian(velocity, 0.5 * (p + moved), t + 0.5 * dt);
            const Vec3d turned = n - dt * jacobian.transpose() * n;
            if (gridlines) RaiseTo(strain_rate, LargestStrainRate(jacobian));
            if (!moved.allFinite() || !turned.allFinite() || !(turned.norm() > 0)) {
              finite = false;
              continue;
            }
            front.points[i] = moved.cast<float>();
            front.normals[i] = turned.normalized().cast<float>();
          }
        },
        &ctx));
    if (!finite) {
      return absl::InvalidArgumentError(core::StrCat("the velocity field gave a non-finite value at step ", step));
    }
    std::vector<ZCrossing> z_crossings;
    log_stretch += strain_rate.load() * dt;
    // Topology changes happen at re-generations, so with merge_distance every step is one: two
    // fronts that merely translate towards each other never stretch.
    // (λ ≥ 0, so regeneration_stretch = 1 re-generates every step.)
    const bool regenerate =
        gridlines && (params.merge_distance > 0 || log_stretch >= std::log(params.regeneration_stretch));
    if (regenerate) {
      // 2. Re-generation on the gridlines, 3. thinning.
      log_stretch = 0;
      auto field = SurfaceFunction(front, h, params.support_factor, params.merge_distance, ctx);
      if (!field.ok()) return field.status();
      auto sampled = SampleGridlines(**field, NodesNear(front.points, h, marks), h, false, ctx);
      if (!sampled.ok()) return sampled.status();
      front = Thin(sampled->crossings, h);
      markers.birth.assign(front.points.size(), step);
      z_crossings = std::move(sampled->z_crossings);
    } else if (!gridlines) {
      // 2. Markers that crowd are thinned, 3. gaps are filled.
      ThinMarkers(markers, params.marker_spacing * h);
      LSQSURF_RETURN_IF_ERROR(FillGaps(markers, step, h, params.marker_gap * h, params.support_factor, ctx));
      if (params.merge_distance > 0) {
        LSQSURF_RETURN_IF_ERROR(
            ReplaceMergingMarkers(markers, step, h, params.support_factor, params.merge_distance, marks, ctx));
      }
    }
    if (front.points.size() < 4) {
      return absl::FailedPreconditionError(
          core::StrCat("the front vanished at step ", step, ": it became thinner than the grid spacing h"));
    }
    if (front.points.size() > params.max_points) {
      return absl::ResourceExhaustedError(core::StrCat("the front grew to ", front.points.size(), " points at step ",
                                                       step, " (limit ", params.max_points,
                                                       "); a finer h resolves thin sheets"));
    }
    ctx.ReportProgress("tracking the front", static_cast<double>(step) / params.steps);
    if (step % params.output_stride == 0 || step == params.steps) {
      stats.step = step;
      stats.time = step * dt;
      stats.points = front.points.size();
      if (!regenerate) {
        auto z = ZCrossings(front, h, h, params.support_factor, params.merge_distance, marks, ctx);
        if (!z.ok()) return z.status();
        z_crossings = std::move(*z);
      }
      stats.volume = VolumeOf(z_crossings, h);
      stats.volume_change = (stats.volume - v0) / v0;
      stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
      LSQSURF_RETURN_IF_ERROR(on_frame(stats, front));
      since = std::chrono::steady_clock::now();
    }
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::front
