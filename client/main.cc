// lsqsurf — command-line client of lsqsurfd: upload clouds, follow jobs, download meshes, and
// compare meshes with the benchmark measures. Parses flags and calls the commands of cli.h.
#include "client/cli.h"

using namespace lsqsurf::cli;  // NOLINT: main wires the commands, nothing else.

namespace {

// render: a mesh result with the view options, or a volume job's field (--volume and friends).
int Render(const Globals& g, const ViewFlags& view, const VolumeViewFlags& volume_view, const std::string& id,
           std::string name, const std::string& output) {
  auto options = view.Options();
  if (!options.ok()) return Fail(std::string(options.status().message()));
  if (volume_view.Requested()) {
    if (absl::Status s = volume_view.Apply(&*options); !s.ok()) return Fail(std::string(s.message()));
    name = kVolumeField;
  }
  return RenderToFile(g, id, name, *options, output);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf: client of the lsqsurfd reconstruction server"};
  app.footer("Defaults and ranges of method parameters and view options: lsqsurf methods, or docs/parameters.md.");
  app.require_subcommand(1);
  Globals g;
  g.AddTo(app);

  SurfaceCommand surface;
  auto* reconstruct = app.add_subcommand("reconstruct", "upload a cloud, wait, and write the mesh");
  reconstruct->add_option("input", surface.input, StrCat("point cloud (", lsqsurf::io::KnownExtensions(), ")"))
      ->required();
  reconstruct->add_option("-o,--output", surface.outputs, "mesh to write (.ply .obj .drc); repeat for several")
      ->required();
  surface.job.AddTo(reconstruct);
  surface.AddPartFlag(reconstruct);
  reconstruct->add_option("--preview", surface.preview, "also render the mesh to this PNG file (view options below)");
  surface.view.AddTo(reconstruct);
  auto* submit = app.add_subcommand("submit", "upload a cloud and print the job id");
  submit->add_option("input", surface.input, "point cloud")->required();
  surface.job.AddTo(submit);
  surface.AddPartFlag(submit);
  surface.volume.AddTo(submit);
  submit->add_flag("--job-preview", surface.job_preview,
                   "the job also draws preview.png into its results (view options below)");
  surface.view.AddTo(submit);

  auto* volume = app.add_subcommand("volume", "upload a volume mesh with scalar fields, wait, and write isosurfaces");
  volume
      ->add_option("input", surface.input,
                   "volume (.vtk legacy VTK, .vtu VTK XML, .ply points with values, raw with --raw)")
      ->required();
  surface.volume.AddTo(volume);
  volume->add_option("--iso", surface.iso, "iso-value of the isosurface (repeatable)");
  volume->add_option("-o,--output", surface.outputs, "isosurface mesh to write (.ply .obj .drc; needs --iso)");
  volume->add_option("--param", surface.job.params, "volume parameter as name=value (lsqsurf methods)");
  volume->add_option("--mesh-bits", surface.job.mesh_bits, "Draco quantization of result positions");

  CLI::App* csg = AddCsgCommand(app, surface);
  CLI::App* edit = AddEditCommand(app, surface);

  ProbeCommand probe_command;
  auto* probe = app.add_subcommand("probe", "values of a finished volume job's field at points or on a grid");
  probe_command.AddTo(probe);

  std::string id, name, output, reference, candidate;
  bool partial = false;
  std::vector<CLI::App*> id_commands;
  for (const auto& [command, help] :
       std::vector<std::pair<const char*, const char*>>{{"watch", "follow a job until it ends"},
                                                        {"status", "show a job"},
                                                        {"cancel", "cancel a queued or running job"},
                                                        {"delete", "delete a finished job and its files"}}) {
    id_commands.push_back(app.add_subcommand(command, help));
    id_commands.back()->add_option("id", id, "job id")->required();
  }
  int limit = 0;
  auto* list = app.add_subcommand("list", "list jobs, newest first");
  list->add_option("--limit", limit, "at most this many");
  auto* fetch = app.add_subcommand("fetch", "download a result");
  fetch->add_option("id", id, "job id")->required();
  fetch->add_option("-o,--output", output, "file to write (.ply .obj .drc; DIR/: a .drc per tile)")->required();
  fetch->add_option("--name", name, "artifact name, e.g. preview.png or stats.csv (default: the mesh)");
  fetch->add_flag("--partial", partial, "of a running job that delivers its mesh in parts, the surface so far");
  auto* methods = app.add_subcommand("methods", "list the server's methods and parameters");
  auto* info = app.add_subcommand("info", "show the server's version and limits");
  HealthCommand health_command;
  CLI::App* health = health_command.AddTo(app);
  TrackCommand track_command;
  auto* track = app.add_subcommand("track", "advect an interface through a velocity field; write frames and stats");
  track_command.AddTo(track);
  for (CLI::App* waits : {reconstruct, volume, csg, edit, probe, track}) g.AddStatsFlag(waits);
  ViewFlags render_view;
  auto* render = app.add_subcommand("render", "render a result (mesh, points or frame) to a PNG picture");
  render->add_option("id", id, "job id")->required();
  render->add_option("-o,--output", output, "PNG file to write")->required();
  render->add_option("--name", name, "artifact name (default: the job's first result)");
  render_view.AddTo(render);
  VolumeViewFlags volume_view;
  volume_view.AddTo(render);
  size_t samples = 1'000'000;
  auto* compare = app.add_subcommand("compare", "Chamfer/Hausdorff distance and normal consistency");
  compare->add_option("reference", reference, "reference mesh")->required();
  compare->add_option("candidate", candidate, "candidate mesh")->required();
  compare->add_option("--samples", samples, "samples per surface")->capture_default_str();
  SampleCommand sample_command;
  CLI::App* sample = sample_command.AddTo(app);
  CLI11_PARSE(app, argc, argv);
  if (*sample) return sample_command.Run();
  if (absl::Status s = g.Resolve(); !s.ok()) return Fail(std::string(s.message()));

  if (*volume) {
    surface.job.method = "volume";
    if (!surface.outputs.empty() && surface.iso.empty()) return Fail("-o writes an isosurface: give --iso VALUE");
    return surface.Run(g, /*wait=*/true);
  }
  if (*reconstruct || *submit) return surface.Run(g, /*wait=*/reconstruct->parsed());
  if (*csg || *edit) {
    surface.job.method = *csg ? "csg" : "edit";
    return surface.Run(g, /*wait=*/true);
  }
  if (*track) return track_command.Run(g);
  if (*probe) return probe_command.Run(g);
  if (*render) return Render(g, render_view, volume_view, id, name, output);
  for (CLI::App* command : id_commands) {
    if (*command) return JobCommand(g, command->get_name(), id);
  }
  if (*list) return List(g, limit);
  if (*fetch) return FetchToFile(g, id, name, output, nullptr, partial);
  if (*methods) return PrintMethods(g);
  if (*info) return PrintServerInfo(g);
  if (*health) return health_command.Run(g);
  if (*compare) return Compare(reference, candidate, samples);
  return Fail("no command given");
}
