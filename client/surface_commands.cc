#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "client/cli.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

absl::Status SurfaceCommand::ApplyEdit(v1::JobSpec* spec) const {
  v1::EditParams& p = *spec->mutable_edit();
  p.set_source(edit.source);
  std::vector<double> ball;
  std::string item;
  for (char c : edit.ball + ",") {
    if (c != ',') {
      item += c;
      continue;
    }
    char* end = nullptr;
    const double v = std::strtod(item.c_str(), &end);
    if (item.empty() || end != item.c_str() + item.size() || !std::isfinite(v)) {
      return absl::InvalidArgumentError(StrCat("--ball '", edit.ball, "': expected x,y,z,r"));
    }
    ball.push_back(v);
    item.clear();
  }
  if (ball.size() != 4) return absl::InvalidArgumentError(StrCat("--ball '", edit.ball, "': expected x,y,z,r"));
  p.set_center_x(ball[0]), p.set_center_y(ball[1]), p.set_center_z(ball[2]), p.set_radius(ball[3]);
  const int actions = (edit.set.empty() ? 0 : 1) + (edit.refit.empty() ? 0 : 1) + (edit.remove ? 1 : 0);
  if (actions != 1)
    return absl::InvalidArgumentError("give one of --set degree=N, --refit error_threshold=E, --remove");
  if (edit.remove) {
    p.set_action(v1::EditParams::ACTION_REMOVE);
    return absl::OkStatus();
  }
  const bool set = !edit.set.empty();
  p.set_action(set ? v1::EditParams::ACTION_SET_DEGREE : v1::EditParams::ACTION_REFIT);
  const std::string& assignment = set ? edit.set : edit.refit;
  const std::string expected = set ? "degree" : "error_threshold";
  if (assignment.rfind(expected + "=", 0) != 0) {
    return absl::InvalidArgumentError(StrCat("--", set ? "set" : "refit", " takes ", expected, "=VALUE"));
  }
  return client::SetParamAssignment(spec, assignment);
}

// The sensor positions a file gives become the job's viewpoint, unless --param viewpoint=... set
// one (an empty one: none); a shift of its coordinates is said, since the mesh keeps it.
absl::Status SurfaceCommand::UseFileFacts(const CloudFileFacts& facts, bool quiet, v1::JobSpec* spec) const {
  if (!quiet && facts.shift != std::array<double, 3>{0, 0, 0}) {
    std::fprintf(stderr,
                 "the file's coordinates are too large for float precision: the points and the mesh are moved by "
                 "(-%s, -%s, -%s); add it back to place the mesh\n",
                 StrCat(facts.shift[0]).c_str(), StrCat(facts.shift[1]).c_str(), StrCat(facts.shift[2]).c_str());
  }
  if (facts.sensors.empty()) return absl::OkStatus();
  for (const std::string& p : job.params) {
    if (p.rfind("viewpoint=", 0) == 0) return absl::OkStatus();
  }
  std::string value;
  for (const lsqsurf::core::Vec3d& s : facts.sensors) {
    StrAppend(&value, value.empty() ? "" : ",", s.x(), ",", s.y(), ",", s.z());
  }
  if (!quiet) {
    if (facts.sensors.size() == 1) {
      std::fprintf(stderr,
                   "the file's sensor stood at (%s): estimated normals face it where it sees the points "
                   "(--param viewpoint= to not)\n",
                   value.c_str());
    } else {
      std::fprintf(stderr,
                   "the file holds %zu scans with their scanners' positions: each point's estimated normal faces "
                   "its own scanner (--param viewpoint= to not)\n",
                   facts.sensors.size());
    }
  }
  return client::SetParam(spec, "viewpoint", value);
}

int SurfaceCommand::Run(const Globals& g, bool wait) const {
  auto spec = job.Spec();
  if (!spec.ok()) return Fail(std::string(spec.status().message()));
  if (job.method == "csg") spec->mutable_csg()->set_expression(csg_expression);
  if (job.method == "edit") {
    if (absl::Status s = ApplyEdit(&*spec); !s.ok()) return Fail(std::string(s.message()));
  }
  const auto view_options = view.Options();
  if (!view_options.ok()) return Fail(std::string(view_options.status().message()));
  if (job_preview) *spec->mutable_preview()->mutable_options() = *view_options;
  client::Client c = Connect(g);
  absl::StatusOr<v1::Job> accepted = absl::UnknownError("");
  if (job.method == "volume") {
    for (double v : iso) spec->mutable_volume()->add_iso(v);
    auto upload = volume.Encode(input, &*spec);
    if (!upload.ok()) return Fail(std::string(upload.status().message()));
    accepted = c.Submit(*spec, upload->input, {}, upload->cells);
  } else {
    CloudFileFacts facts;
    auto parts = CloudUpload(input, part_points, &facts);
    if (!parts.ok()) return Fail(std::string(parts.status().message()));
    if (absl::Status s = UseFileFacts(facts, g.quiet, &*spec); !s.ok()) return Fail(std::string(s.message()));
    // A file that turns out unreadable while it is sent is this side's failure, not the server's.
    absl::Status unreadable;
    accepted = c.SubmitParts(*spec, [&]() -> absl::StatusOr<std::string> {
      auto part = (*parts)();
      if (!part.ok()) unreadable = part.status();
      return part;
    });
    if (!unreadable.ok()) return Fail(std::string(unreadable.message()));
  }
  if (!accepted.ok()) return FailStatus("submit", accepted.status());
  if (!wait) {
    std::printf("%s\n", accepted->id().c_str());
    return 0;
  }
  if (!g.quiet) {
    std::fprintf(stderr, "job %s accepted (%lld points)\n", accepted->id().c_str(),
                 static_cast<long long>(accepted->input_points()));
  }
  v1::Job done;
  if (int rc = Watch(g, accepted->id(), &done); rc != 0) return rc;
  if (outputs.empty()) {  // A volume job kept for later renders and probes.
    if (!g.quiet) PrintStatistics(done, g.all_statistics);
    std::printf("%s\n", done.id().c_str());
    return 0;
  }
  for (const auto& path : outputs) {
    if (int rc = FetchToFile(g, done.id(), "", path, &done); rc != 0) return rc;
  }
  if (!g.quiet) {
    PrintStatistics(done, g.all_statistics);
    for (const auto& path : outputs) std::fprintf(stderr, "wrote %s\n", path.c_str());
  }
  if (!preview.empty()) return RenderToFile(g, done.id(), "", *view_options, preview);
  return 0;
}

// csg: a solid from an expression, run through the surface command's upload-free path.
CLI::App* AddCsgCommand(CLI::App& app, SurfaceCommand& surface) {
  auto* csg = app.add_subcommand("csg", "combine primitives and kept PU results into one solid, wait, write the mesh");
  csg->add_option("expression", surface.csg_expression,
                  "the solid, e.g. 'difference(job:ID, sphere(c=0.1,0.2,0.3 r=0.05))' (README: CSG)")
      ->required();
  csg->add_option("-o,--output", surface.outputs, "mesh to write (.ply .obj .drc); repeat for several")->required();
  csg->add_option("--param", surface.job.params, "csg parameter as name=value, e.g. cell_size=0.002");
  csg->add_option("--mesh-bits", surface.job.mesh_bits, "Draco quantization of result positions");
  csg->add_option("--preview", surface.preview, "also render the mesh to this PNG file (view options below)");
  surface.view.AddTo(csg);
  return csg;
}

// edit: a local edit of a kept PU function, as a new result.
CLI::App* AddEditCommand(CLI::App& app, SurfaceCommand& surface) {
  auto* edit = app.add_subcommand("edit", "edit a pu job's kept function in a ball, wait, write the edited mesh");
  edit->add_option("id", surface.edit.source, "id of a succeeded pu (or edit) job")->required();
  edit->add_option("--ball", surface.edit.ball, "the ball x,y,z,r in model units")->required();
  edit->add_option("--set", surface.edit.set, "degree=N: refit the local fits in the ball at degree N (0..4)");
  edit->add_option("--refit", surface.edit.refit, "error_threshold=E: grow their cells again under E");
  edit->add_flag("--remove", surface.edit.remove, "drop the points and fits in the ball (a hole)");
  edit->add_option("-o,--output", surface.outputs, "mesh to write (.ply .obj .drc); repeat for several")->required();
  edit->add_option("--param", surface.job.params, "extraction parameter as name=value, e.g. cell_size=4");
  edit->add_option("--preview", surface.preview, "also render the mesh to this PNG file (view options below)");
  surface.view.AddTo(edit);
  return edit;
}

void ProbeCommand::AddTo(CLI::App* probe) {
  probe->add_option("id", id, "id of a succeeded volume job")->required();
  probe->add_option("points", points, "points to probe: an XYZ text file, one 'x y z' per line");
  probe->add_option("--grid", grid, "resample on a grid NXxNYxNZ over the field's box instead (writes .vti)");
  probe->add_option("--field", field, "the field to probe (default: the job's first)");
  probe->add_option("-o,--output", output, "values.csv (points) or field.vti (grid)")->required();
}

int ProbeCommand::Run(const Globals& g) const {
  if (points.empty() == grid.empty()) return Fail("give either a POINTS file or --grid NXxNYxNZ");
  v1::JobSpec spec;
  v1::ProbeParams& p = *spec.mutable_probe();
  p.set_source(id);
  if (!field.empty()) p.set_field(field);
  if (!grid.empty()) p.set_grid(grid);
  std::string upload;
  if (!points.empty()) {
    auto cloud = lsqsurf::io::ReadPointCloudFile(points);
    if (!cloud.ok()) return Fail(std::string(cloud.status().message()));
    cloud->normals.clear();
    cloud->attributes.clear();
    // Unquantized and in order: the rows of the answer follow the file's points.
    lsqsurf::io::DracoOptions exact;
    exact.position_bits = 0;
    exact.speed = 10;
    auto encoded = lsqsurf::io::EncodeDracoPointCloud(*cloud, exact);
    if (!encoded.ok()) return Fail(StrCat(points, ": ", encoded.status().message()));
    upload = *std::move(encoded);
  }
  client::Client c = Connect(g);
  auto accepted = c.Submit(spec, upload);
  if (!accepted.ok()) return FailStatus("probe", accepted.status());
  v1::Job done;
  if (int rc = Watch(g, accepted->id(), &done); rc != 0) return rc;
  const std::string artifact = grid.empty() ? "values.csv" : "field.vti";
  auto bytes = c.Fetch(done.id(), artifact);
  if (!bytes.ok()) return FailStatus("fetch", bytes.status());
  if (int rc = WriteResult(*bytes, artifact, output); rc != 0) return rc;
  if (!g.quiet) {
    PrintStatistics(done, g.all_statistics);
    std::fprintf(stderr, "wrote %s\n", output.c_str());
  }
  return 0;
}

}  // namespace lsqsurf::cli
