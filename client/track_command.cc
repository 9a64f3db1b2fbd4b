#include <cmath>
#include <cstdio>
#include <filesystem>

#include "client/cli.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

void TrackCommand::AddTo(CLI::App* track) {
  track->add_option("--interface", interface, "zalesak | sphere | FILE (oriented cloud in the unit cube)");
  track->add_option("--field", field,
                    "rotation (Zalesak) | deformation (Enright) | FILE (legacy VTK STRUCTURED_POINTS with VECTORS)");
  track->add_option("--period", period, "period T of the deformation field");
  track
      ->add_option("--modulation", modulation,
                   "the deformation field in time: cos (times cos(pi t/T), the default) | reversal (full speed, "
                   "reversed at T/2: the seed's test)")
      ->check(CLI::IsMember({"cos", "reversal"}));
  track->add_option("--h", h, "grid spacing; 1/h must be a whole number (the cells parameter)");
  track->add_option("--dt", dt, "time step");
  track->add_option("--steps", steps, "number of steps");
  track->add_option("--stride", stride, "write a frame every this many steps");
  track
      ->add_option("--resampling", resampling,
                   "markers (advected points kept, gaps filled; keeps thin sheets) | gridlines (the seed's "
                   "re-generation on the gridlines)")
      ->check(CLI::IsMember({"markers", "gridlines"}));
  track->add_option("--regeneration-stretch", regeneration_stretch,
                    "gridlines: re-generate once the flow may have spread neighbouring points by this factor "
                    "(default 1.5; 1 = every step, the seed's literal scheme)");
  track->add_option("--support", support, "RAMLS support radius in units of h (default 3)");
  track->add_option("--marker-spacing", marker_spacing,
                    "markers: of two markers facing the same way closer than this (units of h), the younger goes");
  track->add_option("--marker-gap", marker_gap,
                    "markers: a midpoint of two markers with none within this (units of h) gets a new one");
  track->add_option("--max-points", max_points, "fail when the front grows past this many points");
  track->add_option("--merge-distance", merge_distance,
                    "fronts closer than this (units of h) merge and thinner necks pinch off; 0 = never (the "
                    "default), 1.25-1.5 with the default support");
  track->add_flag("--meshes", meshes, "also write a mesh of every frame and its volume (mesh_volume in stats.csv)");
  track->add_option("-o,--output", output, "folder for frame_NNNNN.drc, stats.csv and summary.txt")->required();
  auto* pictures_flag =
      track->add_flag("--pictures", pictures, "also draw every frame to frame_NNNNN.png (view options below)");
  track->add_option("--turntable", turntable, "with --pictures: degrees the camera turns from frame to frame")
      ->needs(pictures_flag);
  view.AddTo(track);
}

absl::StatusOr<v1::JobSpec> TrackCommand::Spec() const {
  v1::JobSpec spec;
  v1::TrackParams& p = *spec.mutable_track();
  if (!interface.empty()) {
    p.set_interface(interface == "sphere"    ? v1::TrackParams::INTERFACE_SPHERE
                    : interface == "zalesak" ? v1::TrackParams::INTERFACE_ZALESAK
                                             : v1::TrackParams::INTERFACE_UPLOADED);
  }
  if (!field.empty()) {
    p.set_field(field == "rotation"      ? v1::TrackParams::FIELD_ROTATION
                : field == "deformation" ? v1::TrackParams::FIELD_DEFORMATION
                                         : v1::TrackParams::FIELD_UPLOADED);
  }
  if (h) {
    const double cells = 1.0 / *h;
    if (!(*h > 0) || std::abs(cells - std::round(cells)) > 1e-6 * cells) {
      return absl::InvalidArgumentError(StrCat("--h ", *h, ": 1/h must be a whole number (e.g. 0.0078125 = 1/128)"));
    }
    p.set_cells(static_cast<int32_t>(std::lround(cells)));
  }
  if (period) p.set_period(*period);
  if (!modulation.empty()) {
    p.set_modulation(modulation == "reversal" ? v1::TrackParams::MODULATION_REVERSAL : v1::TrackParams::MODULATION_COS);
  }
  if (merge_distance) p.set_merge_distance(*merge_distance);
  if (regeneration_stretch) p.set_regeneration_stretch(*regeneration_stretch);
  if (support) p.set_support_factor(*support);
  if (marker_spacing) p.set_marker_spacing(*marker_spacing);
  if (marker_gap) p.set_marker_gap(*marker_gap);
  if (max_points) p.set_max_points(*max_points);
  if (dt) p.set_dt(*dt);
  if (steps) p.set_steps(*steps);
  if (stride) p.set_stride(*stride);
  if (meshes) p.set_meshes(true);
  if (!resampling.empty()) {
    p.set_resampling(resampling == "markers" ? v1::TrackParams::RESAMPLING_MARKERS
                                             : v1::TrackParams::RESAMPLING_GRIDLINES);
  }
  if (pictures) {
    *spec.mutable_preview()->mutable_options() = view.Options();
    spec.mutable_preview()->set_turntable_deg_per_frame(turntable);
  }
  return spec;
}

int TrackCommand::Run(const Globals& g) const {
  auto spec = Spec();
  if (!spec.ok()) return Fail(std::string(spec.status().message()));
  const bool upload_interface = spec->track().interface() == v1::TrackParams::INTERFACE_UPLOADED;
  auto cloud = CloudBytes(upload_interface ? interface : "");
  if (!cloud.ok()) return Fail(std::string(cloud.status().message()));
  std::string velocity;
  if (spec->track().field() == v1::TrackParams::FIELD_UPLOADED) {
    auto raw = lsqsurf::io::ReadFileBytes(field);
    if (!raw.ok()) return Fail(StrCat(field, ": ", raw.status().message()));
    velocity = *std::move(raw);
  }
  client::Client c = Connect(g);
  auto accepted = c.Submit(*spec, *cloud, velocity);
  if (!accepted.ok()) return FailStatus("submit", accepted.status());
  if (!g.quiet) std::fprintf(stderr, "job %s accepted\n", accepted->id().c_str());
  v1::Job done;
  if (int rc = Watch(g, accepted->id(), &done); rc != 0) return rc;
  std::error_code ec;
  std::filesystem::create_directories(output, ec);
  if (ec) return Fail(StrCat("cannot create ", output, ": ", ec.message()));
  for (const std::string& artifact : done.results()) {
    auto bytes = c.Fetch(done.id(), artifact);
    if (!bytes.ok()) return FailStatus("fetch", bytes.status());
    const std::string path = (std::filesystem::path(output) / artifact).string();
    if (absl::Status s = lsqsurf::io::WriteFileAtomically(path, *bytes); !s.ok()) return Fail(std::string(s.message()));
  }
  if (!g.quiet) {
    PrintStatistics(done);
    std::fprintf(stderr, "wrote %d files to %s\n", done.results_size(), output.c_str());
  }
  return 0;
}

}  // namespace lsqsurf::cli
