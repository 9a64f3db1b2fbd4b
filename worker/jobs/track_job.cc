#include "worker/jobs/track_job.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <optional>

#include "worker/core/mesh_metrics.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/io/vtk_grid.h"
#include "worker/jobs/pictures.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {
namespace {

constexpr double kRevolution = 628.0;  // Time units of one turn of Zalesak's rotation.

const core::ParamTable<TrackJobParams>& TrackTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<TrackJobParams>();
    t->Choice<&TrackJobParams::interface>(
         "interface",
         {{"uploaded", static_cast<int>(TrackInterface::kUploaded), "the uploaded oriented cloud (normals outward)"},
          {"sphere", static_cast<int>(TrackInterface::kSphere), "sphere r = 0.15 at (0.35, 0.35, 0.35)"},
          {"zalesak", static_cast<int>(TrackInterface::kZalesak), "Zalesak's slotted sphere"}},
         "the initial interface")
        .Choice<&TrackJobParams::field>(
            "field",
            {{"rotation", static_cast<int>(TrackField::kRotation), "Zalesak's rotation about (0.5, 0.5, z)"},
             {"deformation", static_cast<int>(TrackField::kDeformation), "Enright's 3D deformation"},
             {"uploaded", static_cast<int>(TrackField::kUploaded),
              "the uploaded velocity grid (legacy VTK, trilinear, constant in time)"}},
            "the velocity field")
        .Real<&TrackJobParams::period>("period", 0.01, 1000, "time units",
                                       "period T of the deformation field; the shape returns at t = T")
        .Choice<&TrackJobParams::modulation>(
            "modulation",
            {{"cos", static_cast<int>(front::TimeModulation::kCosine), "the field times cos(pi t / T) (Enright's)"},
             {"reversal", static_cast<int>(front::TimeModulation::kReversal),
              "the field at full speed, reversed at T/2 (the seed's deformation test; stretches further)"}},
            "how the deformation field changes in time")
        .Integer<&TrackJobParams::cells>("cells", 8, 512, "per unit length", "background grid cells (h = 1/cells)")
        .Include(&TrackJobParams::tracking, front::TrackingParamTable(), {"h"})
        .Flag<&TrackJobParams::meshes>("meshes",
                                       "also write frame_NNNNN_mesh.drc (the RAMLS surface on cubes of edge h) and a "
                                       "mesh_volume column in stats.csv, which cross-checks the gridline volume")
        .AddRule([](const TrackJobParams& p) {
          front::TrackingParams tp = p.tracking;
          tp.h = 1.0 / p.cells;
          return front::Validate(tp);
        });
    return t;
  }();
  return *table;
}

absl::StatusOr<front::Front> InitialFront(const TrackJobParams& p, const core::PointCloud* uploaded) {
  if (p.interface == TrackInterface::kUploaded) {
    if (uploaded == nullptr || !uploaded->has_normals()) {
      return absl::InvalidArgumentError("interface=uploaded tracks the uploaded cloud, which needs oriented normals");
    }
    front::Front initial;
    initial.points = uploaded->positions;
    initial.normals = uploaded->normals;
    for (auto& n : initial.normals) n.normalize();
    return initial;
  }
  return front::SampleInitialFront(
      p.interface == TrackInterface::kSphere ? front::InitialShape::kSphere : front::InitialShape::kZalesakSphere,
      1.0 / p.cells);
}

absl::StatusOr<std::unique_ptr<front::VelocityField>> MakeField(const TrackJobParams& p, const io::VectorGrid* grid) {
  switch (p.field) {
    case TrackField::kRotation: return front::ZalesakRotation();
    case TrackField::kDeformation: return front::EnrightDeformation(p.period, p.modulation);
    case TrackField::kUploaded:
      if (grid == nullptr) return absl::InvalidArgumentError("field=uploaded needs an uploaded velocity grid");
      return front::GridVelocity(grid->origin, grid->spacing, grid->dims[0], grid->dims[1], grid->dims[2],
                                 grid->values);
  }
  return absl::InvalidArgumentError("unknown field");
}

// Frame pictures share one box, so that the sequence plays without jumps in scale.
core::Box3 TrackingDomain(const TrackJobParams& p, const io::VectorGrid* grid) {
  if (p.field != TrackField::kUploaded || grid == nullptr) return core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones());
  const core::Vec3d extent(grid->spacing.x() * (grid->dims[0] - 1), grid->spacing.y() * (grid->dims[1] - 1),
                           grid->spacing.z() * (grid->dims[2] - 1));
  return core::Box3(grid->origin, grid->origin + extent);
}

std::string FrameName(int step, const char* suffix) {
  char name[40];
  std::snprintf(name, sizeof(name), "frame_%05d%s", step, suffix);
  return name;
}

// Writes the frames, the table and the pictures of one run.
class FrameWriter {
 public:
  FrameWriter(const TrackJobParams& p, const PreviewSpec& preview, const io::VectorGrid* grid, RunEnvironment& env)
      : params_(p), env_(env) {
    csv_ = p.meshes ? "step,time,points,volume,volume_change,mesh_volume\n" : "step,time,points,volume,volume_change\n";
    if (!preview.enabled) return;
    const auto* view = preview.view.As<render::RenderParams>();
    if (view == nullptr) return;
    picture_ = *view;
    picture_->camera.framing_box = TrackingDomain(p, grid);
    turntable_ = preview.turntable_deg_per_frame;
    if (env.renderer != nullptr) {
      auto r = env.renderer->Get();
      if (r.ok()) renderer_ = *r;
      // Without a renderer every picture counts as failed; the frames themselves still come.
      if (!r.ok()) spdlog::warn("no frame pictures: {}", r.status().message());
    }
  }

  absl::Status Frame(const front::FrameStats& s, const front::Front& f) {
    core::PointCloud cloud;
    cloud.positions = f.points;
    cloud.normals = f.normals;
    auto encoded = io::EncodeDracoPointCloud(cloud, {});
    if (!encoded.ok()) return encoded.status();
    LSQSURF_RETURN_IF_ERROR(env_.sink.Write(FrameName(s.step, ".drc"), *encoded));
    char row[192];
    std::snprintf(row, sizeof(row), "%d,%.9g,%zu,%.9g,%.9g", s.step, s.time, s.points, s.volume, s.volume_change);
    csv_ += row;
    if (!params_.meshes) {
      Draw(cloud, s.step);
    } else {
      auto mesh = front::FrontMesh(f, 1.0 / params_.cells, env_.context, params_.tracking.support_factor,
                                   params_.tracking.merge_distance);
      if (!mesh.ok()) return mesh.status();
      Draw(*mesh, s.step);
      auto encoded_mesh = io::EncodeDracoMesh(*mesh, {});
      if (!encoded_mesh.ok()) return encoded_mesh.status();
      LSQSURF_RETURN_IF_ERROR(env_.sink.Write(FrameName(s.step, "_mesh.drc"), *encoded_mesh));
      std::snprintf(row, sizeof(row), ",%.9g", core::EnclosedVolume(*mesh));
      csv_ += row;
    }
    csv_ += "\n";
    return absl::OkStatus();
  }

  absl::Status Finish() { return env_.sink.Write("stats.csv", csv_); }
  const PreviewFailures& failures() const { return failures_; }

 private:
  template <class Geometry>
  void Draw(const Geometry& geometry, int step) {
    if (!picture_) return;
    render::RenderParams p = *picture_;
    p.camera.azimuth_deg += pictures_drawn_ * turntable_;
    ++pictures_drawn_;
    const std::string name = FrameName(step, ".png");
    absl::StatusOr<std::string> png = absl::UnavailableError("no renderer");
    if (renderer_ != nullptr) png = PicturePng(*renderer_, geometry, p);
    const absl::Status s = png.ok() ? env_.sink.Write(name, *png) : png.status();
    if (!s.ok()) failures_.Add(name, s);
  }

  const TrackJobParams& params_;
  RunEnvironment& env_;
  std::optional<render::RenderParams> picture_;
  double turntable_ = 0;
  render::Renderer* renderer_ = nullptr;
  int pictures_drawn_ = 0;
  PreviewFailures failures_;
  std::string csv_;
};

// The uploads a track job's parameters call for, decoded and checked.
struct TrackInput {
  std::optional<core::PointCloud> interface;  // interface=uploaded.
  std::optional<io::VectorGrid> grid;         // field=uploaded.
};

// An allowance per front point: its position and normal, the four RK4 stages, the index and
// the RAMLS fits' neighbour lists that the resampling builds over it.
constexpr int64_t kTrackBytesPerPoint = 256;

class TrackKind final : public TypedJobKind<TrackJobParams, TrackInput> {
 public:
  std::string_view name() const override { return "track"; }

  std::vector<MethodInfo> Methods() const override {
    return {{"track",
             "front tracking (seed §3): advects an interface with RK4 and keeps it sampled through its RAMLS surface "
             "every step (markers, or the seed's gridline re-generation); results are frames, stats.csv and "
             "summary.txt",
             core::ParamSet(TrackTable()),
             {},
             {kInputUpload, kVelocityUpload}}};
  }

  absl::StatusOr<Checked> Decode(const JobSpec&, const TrackJobParams& p, const Uploads& uploads,
                                 const InputLimits& limits) const override {
    auto input = DecodeInput(p, uploads, limits.max_points);
    if (!input.ok()) return input.status();
    const auto points = static_cast<int64_t>(input->interface ? input->interface->size() : 0);
    // The engine stops a front that grows past max_points; that front must fit.
    const MemoryEstimate memory{static_cast<int64_t>(p.tracking.max_points) * kTrackBytesPerPoint, "lower max_points"};
    return Checked{points, *std::move(input), memory};
  }

  absl::StatusOr<Statistics> RunDecoded(const JobSpec& spec, const TrackJobParams& p, TrackInput input,
                                        RunEnvironment& env) const override {
    LSQSURF_RETURN_IF_ERROR(spec.params.Validate());
    return Track(p, spec.preview, input.interface ? &*input.interface : nullptr, input.grid ? &*input.grid : nullptr,
                 env);
  }

 private:
  static absl::StatusOr<TrackInput> DecodeInput(const TrackJobParams& p, const Uploads& uploads, int64_t max_points) {
    TrackInput input;
    const bool has_input = uploads.contains(kInputUpload) && !uploads.at(kInputUpload).empty();
    if (p.interface == TrackInterface::kUploaded) {
      auto cloud = DecodeInterface(uploads, max_points);
      if (!cloud.ok()) return cloud.status();
      if (cloud->empty()) return absl::InvalidArgumentError("the uploaded interface is empty");
      if (static_cast<int64_t>(cloud->size()) > max_points) {
        return absl::ResourceExhaustedError(
            core::StrCat("the interface has ", cloud->size(), " points; this server accepts at most ", max_points));
      }
      if (const int64_t bad = core::FindNonFinite(cloud->positions); bad >= 0) {
        return absl::InvalidArgumentError(core::StrCat("point ", bad, " has a NaN or infinite coordinate"));
      }
      input.interface = *std::move(cloud);
    } else if (has_input) {
      return absl::InvalidArgumentError("a cloud was uploaded, but interface is a named shape; set interface=uploaded");
    }
    const bool has_velocity = uploads.contains(kVelocityUpload) && !uploads.at(kVelocityUpload).empty();
    if (p.field == TrackField::kUploaded) {
      if (!has_velocity) {
        return absl::InvalidArgumentError(
            "field=uploaded tracks through an uploaded velocity grid, but none was uploaded");
      }
      auto grid = io::ParseVtkVectorGrid(uploads.at(kVelocityUpload), "velocity");
      if (!grid.ok()) return grid.status();
      input.grid = *std::move(grid);
    } else if (has_velocity) {
      return absl::InvalidArgumentError("a velocity grid was uploaded, but only field=uploaded uses one");
    }
    return input;
  }

  static absl::StatusOr<core::PointCloud> DecodeInterface(const Uploads& uploads, int64_t max_points) {
    auto it = uploads.find(kInputUpload);
    if (it == uploads.end() || it->second.empty()) {
      return absl::InvalidArgumentError("interface=uploaded needs an uploaded oriented cloud");
    }
    auto cloud = io::DecodeDracoPointCloud(it->second, {.max_points = max_points});
    if (!cloud.ok()) return core::WithContext("input", cloud.status());
    if (!cloud->has_normals())
      return absl::InvalidArgumentError("a tracked interface needs oriented normals (outward)");
    return cloud;
  }

  static absl::StatusOr<Statistics> Track(const TrackJobParams& p, const PreviewSpec& preview,
                                          const core::PointCloud* cloud, const io::VectorGrid* grid,
                                          RunEnvironment& env) {
    front::TrackingParams tp = p.tracking;
    tp.h = 1.0 / p.cells;
    auto initial = InitialFront(p, cloud);
    if (!initial.ok()) return initial.status();
    auto field = MakeField(p, grid);
    if (!field.ok()) return field.status();
    FrameWriter writer(p, preview, grid, env);
    front::Front last;
    front::FrameStats last_stats;
    double v0 = 0;
    const auto start = std::chrono::steady_clock::now();
    LSQSURF_RETURN_IF_ERROR(front::Track(*initial, **field, tp, env.context,
                                         [&](const front::FrameStats& s, const front::Front& f) -> absl::Status {
                                           LSQSURF_RETURN_IF_ERROR(writer.Frame(s, f));
                                           if (s.step == 0) v0 = s.volume;
                                           last = f;
                                           last_stats = s;
                                           return absl::OkStatus();
                                         }));
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    LSQSURF_RETURN_IF_ERROR(writer.Finish());
    Statistics stats = {{"steps", tp.steps},
                        {"final_points", static_cast<double>(last_stats.points)},
                        {"volume_change", last_stats.volume_change},
                        {"tracking_seconds", seconds}};
    LSQSURF_RETURN_IF_ERROR(writer.failures().Report(env, stats));
    // A named shape back where a named field returns it: measure E1 against the exact shape.
    const double end_time = tp.steps * tp.dt;
    const bool deformation = p.field == TrackField::kDeformation;
    const double back_at = deformation ? p.period : kRevolution * std::max(1.0, std::round(end_time / kRevolution));
    if (p.interface != TrackInterface::kUploaded && p.field != TrackField::kUploaded &&
        std::abs(end_time - back_at) <= 1e-6 * back_at) {
      const front::InitialShape exact =
          p.interface == TrackInterface::kSphere ? front::InitialShape::kSphere : front::InitialShape::kZalesakSphere;
      auto e1 = front::ShapeError(last, exact, tp.h, tp.support_factor, tp.merge_distance);
      if (!e1.ok()) return e1.status();
      const double e1_rel = *e1 / v0;
      char summary[128];
      std::snprintf(summary, sizeof(summary), "e1_rel=%.6g volume_change=%.6g\n", e1_rel, last_stats.volume_change);
      LSQSURF_RETURN_IF_ERROR(env.sink.Write("summary.txt", summary));
      stats.emplace_back("e1_rel", e1_rel);
    }
    return stats;
  }
};

}  // namespace

const JobKind& TrackJobKind() {
  static const TrackKind kind;
  return kind;
}

}  // namespace lsqsurf::jobs
