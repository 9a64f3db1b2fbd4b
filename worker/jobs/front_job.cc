#include "worker/jobs/front_job.h"

#include <chrono>
#include <cmath>
#include <cstdio>

#include <spdlog/spdlog.h>

#include "worker/core/mesh_metrics.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/front/front_tracking.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/jobs/pictures.h"

namespace lsqsurf::jobs {
namespace {

constexpr int kUploaded = 0, kSphere = 1;  // interface=2: Zalesak.
constexpr int kRotation = 0, kDeformation = 1, kUploadedField = 2;
constexpr double kRevolution = 628.0;  // Time units of one turn of Zalesak's rotation.

double Param(const ParameterMap& parameters, const char* name) {
  return ParameterOrDefault(kTrackMethod, parameters, name);
}

}  // namespace

MethodSpec TrackMethod() {
  const front::TrackingParams p;
  MethodSpec m{kTrackMethod,
               "front tracking (seed §3): advects an interface with RK4 and keeps it sampled through its RAMLS "
               "surface every step (markers, or the seed's gridline re-generation); results are frames, stats.csv "
               "and summary.txt",
               {}, {}};
  m.parameters = {
      {"interface", kUploaded, 0, 2, true, "0: the uploaded oriented cloud; 1: sphere r=0.15 at (0.35,0.35,0.35); "
                                           "2: Zalesak's slotted sphere"},
      {"field", kRotation, 0, 2, true, "0: Zalesak's rotation about (0.5, 0.5, z); 1: Enright's 3D deformation; "
                                       "2: the uploaded velocity grid (legacy VTK, trilinear, constant in time)"},
      {"period", 3, 0.01, 1000, false, "period T of the deformation field, cos(pi t / T) modulation"},
      {"cells", std::round(1 / p.h), 8, 512, true, "background grid cells per unit length (h = 1/cells)"},
      {"dt", p.dt, 1e-6, 1000, false, "time step"},
      {"steps", 100, 1, 100000, true, "number of steps"},
      {"stride", 10, 1, 100000, true, "write a frame every this many steps (and after the last)"},
      {"support_factor", p.support_factor, 1.5, 10, false, "RAMLS support radius in units of h"},
      {"resampling", p.resampling == front::Resampling::kMarkers ? 1.0 : 0.0, 0, 1, true,
       "1: markers (the advected points stay; crowded ones are thinned, stretched gaps filled from the RAMLS "
       "surface of their side; keeps sheets thinner than h); 0: the seed's re-generation on the gridlines every "
       "step"},
      {"marker_spacing", p.marker_spacing, 0.1, 1, false,
       "resampling=1: of two markers facing the same way closer than this (units of h), the younger goes"},
      {"marker_gap", p.marker_gap, 0.15, 1, false,
       "resampling=1: a midpoint of two markers with no marker within this (units of h) gets a new one; "
       "must exceed marker_spacing"},
      {"max_points", static_cast<double>(p.max_points), 100, 50'000'000, true,
       "stop with an error if the front grows past this many points"},
      {"meshes", 0, 0, 1, true, "1: also write frame_NNNNN_mesh.drc (the RAMLS surface on cubes of edge h) and "
                                "a mesh_volume column in stats.csv, which cross-checks the gridline volume"},
  };
  return m;
}

bool TrackNeedsUpload(const ParameterMap& parameters) { return static_cast<int>(Param(parameters, "interface")) == kUploaded; }

bool TrackNeedsVelocity(const ParameterMap& parameters) {
  return static_cast<int>(Param(parameters, "field")) == kUploadedField;
}

absl::StatusOr<TrackOutput> RunTrackJob(const ParameterMap& parameters, const core::PointCloud* interface,
                                        const io::VectorGrid* velocity, const std::string& out_dir,
                                        core::JobContext& ctx, const FramePictures* pictures) {
  LSQSURF_RETURN_IF_ERROR(ValidateRequest(kTrackMethod, parameters));
  const int shape = static_cast<int>(Param(parameters, "interface"));
  front::TrackingParams tp;
  tp.h = 1.0 / Param(parameters, "cells");
  tp.dt = Param(parameters, "dt");
  tp.steps = static_cast<int>(Param(parameters, "steps"));
  tp.output_stride = static_cast<int>(Param(parameters, "stride"));
  tp.support_factor = Param(parameters, "support_factor");
  tp.max_points = static_cast<size_t>(Param(parameters, "max_points"));
  tp.resampling = Param(parameters, "resampling") != 0 ? front::Resampling::kMarkers : front::Resampling::kGridlines;
  tp.marker_spacing = Param(parameters, "marker_spacing");
  tp.marker_gap = Param(parameters, "marker_gap");
  LSQSURF_RETURN_IF_ERROR(front::Validate(tp));
  const double period = Param(parameters, "period");
  const int field_kind = static_cast<int>(Param(parameters, "field"));
  const bool deformation = field_kind == kDeformation;

  front::Front initial;
  if (shape == kUploaded) {
    if (interface == nullptr || !interface->has_normals()) {
      return absl::InvalidArgumentError("interface=0 tracks the uploaded cloud, which needs oriented normals");
    }
    initial.points = interface->positions;
    initial.normals = interface->normals;
    for (auto& n : initial.normals) n.normalize();
  } else {
    auto sampled = front::SampleInitialFront(shape == kSphere ? front::InitialShape::kSphere
                                                              : front::InitialShape::kZalesakSphere,
                                             tp.h);
    if (!sampled.ok()) return sampled.status();
    initial = *std::move(sampled);
  }
  std::unique_ptr<front::VelocityField> field;
  if (field_kind == kUploadedField) {
    if (velocity == nullptr) return absl::InvalidArgumentError("field=2 needs an uploaded velocity grid");
    auto grid = front::GridVelocity(velocity->origin, velocity->spacing, velocity->dims[0], velocity->dims[1],
                                    velocity->dims[2], velocity->values);
    if (!grid.ok()) return grid.status();
    field = *std::move(grid);
  } else {
    field = deformation ? front::EnrightDeformation(period) : front::ZalesakRotation();
  }

  TrackOutput out;
  const bool meshes = Param(parameters, "meshes") != 0;
  // Every picture frames the same box, so that the sequence plays without jumps in scale.
  render::RenderParams picture;
  if (pictures != nullptr) {
    picture = pictures->params;
    picture.camera.framing_box = core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones());
    if (field_kind == kUploadedField) {
      const core::Vec3d extent(velocity->spacing.x() * (velocity->dims[0] - 1), velocity->spacing.y() * (velocity->dims[1] - 1),
                               velocity->spacing.z() * (velocity->dims[2] - 1));
      picture.camera.framing_box = core::Box3(velocity->origin, velocity->origin + extent);
    }
  }
  int pictures_drawn = 0, picture_failures = 0;
  auto draw = [&](const auto& geometry, int step) {
    char name[32];
    std::snprintf(name, sizeof(name), "frame_%05d.png", step);
    render::RenderParams p = picture;
    p.camera.azimuth_deg += pictures_drawn * pictures->turntable_deg_per_frame;
    ++pictures_drawn;
    const absl::Status s = pictures->renderer != nullptr ? WritePicture(*pictures->renderer, geometry, p, out_dir + "/" + name)
                                                         : absl::UnavailableError("no renderer");
    if (!s.ok()) {
      ++picture_failures;  // The frames and statistics are what the job is for; a picture is not.
      spdlog::warn("{} not drawn: {}", name, s.message());
      return;
    }
    out.artifacts.push_back(name);
  };
  std::string csv = meshes ? "step,time,points,volume,volume_change,mesh_volume\n" : "step,time,points,volume,volume_change\n";
  front::Front last;
  front::FrameStats last_stats;
  double v0 = 0;
  const auto start = std::chrono::steady_clock::now();
  LSQSURF_RETURN_IF_ERROR(front::Track(initial, *field, tp, ctx,
                                       [&](const front::FrameStats& s, const front::Front& f) -> absl::Status {
    core::PointCloud cloud;
    cloud.positions = f.points;
    cloud.normals = f.normals;
    auto encoded = io::EncodeDracoPointCloud(cloud, {});
    if (!encoded.ok()) return encoded.status();
    char name[32];
    std::snprintf(name, sizeof(name), "frame_%05d.drc", s.step);
    if (absl::Status w = io::WriteFileAtomically(out_dir + "/" + name, *encoded); !w.ok()) {
      return absl::UnavailableError(core::StrCat("cannot write ", name, ": ", w.message()));
    }
    out.artifacts.push_back(name);
    char row[192];
    std::snprintf(row, sizeof(row), "%d,%.9g,%zu,%.9g,%.9g", s.step, s.time, s.points, s.volume, s.volume_change);
    csv += row;
    if (pictures != nullptr && !meshes) draw(cloud, s.step);
    if (meshes) {
      auto mesh = front::FrontMesh(f, tp.h, ctx, tp.support_factor);
      if (!mesh.ok()) return mesh.status();
      if (pictures != nullptr) draw(*mesh, s.step);
      auto encoded_mesh = io::EncodeDracoMesh(*mesh, {});
      if (!encoded_mesh.ok()) return encoded_mesh.status();
      std::snprintf(name, sizeof(name), "frame_%05d_mesh.drc", s.step);
      if (absl::Status w = io::WriteFileAtomically(out_dir + "/" + name, *encoded_mesh); !w.ok()) {
        return absl::UnavailableError(core::StrCat("cannot write ", name, ": ", w.message()));
      }
      out.artifacts.push_back(name);
      std::snprintf(row, sizeof(row), ",%.9g", core::EnclosedVolume(*mesh));
      csv += row;
    }
    csv += "\n";
    if (s.step == 0) v0 = s.volume;
    last = f;
    last_stats = s;
    return absl::OkStatus();
  }));
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  LSQSURF_RETURN_IF_ERROR(io::WriteFileAtomically(out_dir + "/stats.csv", csv));
  out.artifacts.push_back("stats.csv");
  out.statistics = {{"steps", tp.steps},
                    {"final_points", static_cast<double>(last_stats.points)},
                    {"volume_change", last_stats.volume_change},
                    {"tracking_seconds", seconds}};
  if (picture_failures > 0) out.statistics.emplace_back("preview_failures", picture_failures);
  // A named shape back where a named field returns it: measure E1 against the exact shape.
  const double end_time = tp.steps * tp.dt;
  const double back_at = deformation ? period : kRevolution * std::max(1.0, std::round(end_time / kRevolution));
  if (shape != kUploaded && field_kind != kUploadedField && std::abs(end_time - back_at) <= 1e-6 * back_at) {
    const front::InitialShape exact = shape == kSphere ? front::InitialShape::kSphere : front::InitialShape::kZalesakSphere;
    auto e1 = front::ShapeError(last, exact, tp.h, tp.support_factor);
    if (!e1.ok()) return e1.status();
    const double e1_rel = *e1 / v0;
    char summary[128];
    std::snprintf(summary, sizeof(summary), "e1_rel=%.6g volume_change=%.6g\n", e1_rel, last_stats.volume_change);
    LSQSURF_RETURN_IF_ERROR(io::WriteFileAtomically(out_dir + "/summary.txt", summary));
    out.artifacts.push_back("summary.txt");
    out.statistics.emplace_back("e1_rel", e1_rel);
  }
  return out;
}

}  // namespace lsqsurf::jobs
