#include <cmath>
#include <cstdio>
#include <filesystem>

#include "client/cli.h"
#include "worker/core/status.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

void TrackCommand::AddTo(CLI::App* track) {
  track->add_option(
      "--interface", interface,
      StrCat("zalesak | sphere | FILE (an oriented cloud in the unit cube); ", TableHelp("track", "interface")));
  track->add_option("--field", field,
                    "rotation (Zalesak) | deformation (Enright) | FILE (legacy VTK STRUCTURED_POINTS with VECTORS)");
  track->add_option("--h", h, "grid spacing, 1/cells; 1/h must be a whole number (or give --cells)");
  params.AddTo(track, {.aliases = {{"support_factor", "--support"}}, .skip = {"interface", "field"}});
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
  LSQSURF_RETURN_IF_ERROR(params.Apply(&p));
  if (pictures) {
    LSQSURF_ASSIGN_OR_RETURN(*spec.mutable_preview()->mutable_options(), view.Options());
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
    PrintStatistics(done, g.all_statistics);
    std::fprintf(stderr, "wrote %d files to %s\n", done.results_size(), output.c_str());
  }
  return 0;
}

}  // namespace lsqsurf::cli
