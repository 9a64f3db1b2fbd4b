// lsqsurf — command-line client of lsqsurfd: upload clouds, follow jobs, download meshes,
// and compare meshes with the benchmark measures.
#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <cstdlib>
#include <iostream>
#include <optional>

#include <CLI/CLI.hpp>

#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "worker/core/strings.h"
#include "worker/core/surface_distance.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace {

namespace v1 = lsqsurf::v1;
using lsqsurf::core::StrCat;

// Exit codes: 0 success; 1 the job failed or the server refused the request; 2 the job was
// cancelled; 3 a local problem (bad file, unreachable server, usage).
constexpr int kExitFailed = 1;
constexpr int kExitCancelled = 2;
constexpr int kExitLocal = 3;

int Fail(const std::string& message, int code = kExitLocal) {
  std::fprintf(stderr, "lsqsurf: %s\n", message.c_str());
  return code;
}

int FailRpc(const char* what, const grpc::Status& s) {
  const int code = s.error_code() == grpc::StatusCode::UNAVAILABLE ? kExitLocal : kExitFailed;
  return Fail(StrCat(what, ": ", s.error_message(), " (", static_cast<int>(s.error_code()), ")"), code);
}

const char* StateName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_QUEUED: return "queued";
    case v1::JOB_STATE_RUNNING: return "running";
    case v1::JOB_STATE_SUCCEEDED: return "succeeded";
    case v1::JOB_STATE_FAILED: return "failed";
    case v1::JOB_STATE_CANCELLED: return "cancelled";
    default: return "unknown";
  }
}

bool Terminal(v1::JobState s) {
  return s == v1::JOB_STATE_SUCCEEDED || s == v1::JOB_STATE_FAILED || s == v1::JOB_STATE_CANCELLED;
}

struct Options {
  std::string server;
  std::string method = "iamls";
  std::vector<std::string> params;
  int mesh_bits = 0;
  bool quiet = false;
  std::optional<v1::PreviewSpec> preview;  // Pictures the job draws into its results.
};

// View options shared by render, reconstruct --preview, submit --job-preview and track
// --pictures. Options left out are not sent: the server's defaults (RenderOptions) apply.
struct ViewFlags {
  int size = 0, samples = 0;
  std::optional<double> azimuth, elevation, distance, fov;
  std::string up, color;
  bool flat = false, wireframe = false, transparent = false;

  void AddTo(CLI::App* cmd) {
    cmd->add_option("--size", size, "picture width and height in pixels, 16..4096 (default 1024)");
    cmd->add_option("--up", up, "axis pointing up in the picture: x, y or z (default z; scans are often y)");
    cmd->add_option("--azimuth", azimuth, "camera degrees about the up axis (default 35)");
    cmd->add_option("--elevation", elevation, "camera degrees above the plane normal to the up axis (default 25)");
    cmd->add_option("--distance", distance, "camera distance from the box centre (default: frame the model)");
    cmd->add_option("--fov", fov, "vertical field of view in degrees (default 30)");
    cmd->add_option("--color", color, "per-vertex attribute to colour by, e.g. degree or depth (PU meshes)");
    cmd->add_flag("--flat", flat, "flat shading (one normal per triangle)");
    cmd->add_flag("--wireframe", wireframe, "draw the triangle edges");
    cmd->add_flag("--transparent", transparent, "transparent background");
    cmd->add_option("--samples", samples, "MSAA samples per pixel: 1, 2, 4 or 8 (default 4)");
  }

  v1::RenderOptions Options() const {
    v1::RenderOptions view;
    view.set_width(size);
    view.set_height(size);
    if (azimuth) view.set_azimuth_deg(*azimuth);
    if (elevation) view.set_elevation_deg(*elevation);
    if (distance) view.set_distance(*distance);
    if (fov) view.set_fov_deg(*fov);
    view.set_up_axis(up);
    view.set_color(color);
    view.set_flat_shading(flat);
    view.set_wireframe(wireframe);
    view.set_transparent(transparent);
    view.set_samples(samples);
    return view;
  }
};

std::unique_ptr<v1::Reconstruction::Stub> Connect(const Options& o) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(16 << 20);
  args.SetMaxSendMessageSize(16 << 20);
  return v1::Reconstruction::NewStub(grpc::CreateCustomChannel(o.server, grpc::InsecureChannelCredentials(), args));
}

// Parses "name=value" pairs; values are numbers, or true/false for flags.
bool ParseParams(const std::vector<std::string>& pairs, v1::JobSpec* spec, std::string* error) {
  for (const auto& p : pairs) {
    const size_t eq = p.find('=');
    if (eq == std::string::npos || eq == 0) {
      *error = StrCat("--param expects name=value, got '", p, "'");
      return false;
    }
    const std::string name = p.substr(0, eq), text = p.substr(eq + 1);
    double value = 0;
    if (text == "true") value = 1;
    else if (text == "false") value = 0;
    else {
      char* end = nullptr;
      value = std::strtod(text.c_str(), &end);
      if (text.empty() || *end != '\0') {
        *error = StrCat("--param ", name, ": '", text, "' is not a number");
        return false;
      }
    }
    (*spec->mutable_parameters())[name] = value;
  }
  return true;
}

// Uploads `path` as a Draco cloud (nothing when `path` is empty) and the file `velocity_path` as
// the velocity grid (when not empty); returns the accepted job or an exit code.
int Submit(const Options& o, const std::string& path, v1::Job* job, const std::string& velocity_path = {}) {
  v1::JobSpec spec;
  spec.set_method(o.method);
  spec.set_mesh_position_bits(o.mesh_bits);
  if (o.preview) *spec.mutable_preview() = *o.preview;
  std::string error;
  if (!ParseParams(o.params, &spec, &error)) return Fail(error);
  std::string bytes;
  if (path.empty()) {
    // A job that needs no input (a front-tracking job of a named shape).
  } else if (lsqsurf::io::FormatFromPath(path).value_or(lsqsurf::io::FileFormat::kPly) == lsqsurf::io::FileFormat::kDraco) {
    auto raw = lsqsurf::io::ReadFileBytes(path);
    if (!raw.ok()) return Fail(std::string(raw.status().message()));
    bytes = *std::move(raw);
  } else {
    auto cloud = lsqsurf::io::ReadPointCloudFile(path);
    if (!cloud.ok()) return Fail(std::string(cloud.status().message()));
    auto encoded = lsqsurf::io::EncodeDracoPointCloud(*cloud, {});
    if (!encoded.ok()) return Fail(StrCat(path, ": ", encoded.status().message()));
    bytes = *std::move(encoded);
  }
  std::string velocity;
  if (!velocity_path.empty()) {
    auto raw = lsqsurf::io::ReadFileBytes(velocity_path);
    if (!raw.ok()) return Fail(StrCat(velocity_path, ": ", raw.status().message()));
    velocity = *std::move(raw);
  }
  auto stub = Connect(o);
  grpc::ClientContext ctx;
  auto writer = stub->SubmitJob(&ctx, job);
  v1::SubmitJobRequest request;
  *request.mutable_spec() = spec;
  bool open = writer->Write(request);
  constexpr size_t kChunk = size_t{1} << 20;
  for (size_t offset = 0; open && offset < bytes.size(); offset += kChunk) {
    request.set_input_chunk(bytes.substr(offset, kChunk));
    open = writer->Write(request);
  }
  for (size_t offset = 0; open && offset < velocity.size(); offset += kChunk) {
    request.set_velocity_chunk(velocity.substr(offset, kChunk));
    open = writer->Write(request);
  }
  writer->WritesDone();
  const grpc::Status status = writer->Finish();
  if (!status.ok()) return FailRpc("submit", status);
  return 0;
}

void PrintProgress(const v1::Job& job, bool tty, std::string* last_line) {
  if (tty) {
    const int width = 30;
    const int filled = static_cast<int>(std::lround(job.progress() * width));
    std::fprintf(stderr, "\r[%s%s] %3d%% %-28s", std::string(static_cast<size_t>(filled), '#').c_str(),
                 std::string(static_cast<size_t>(width - filled), '.').c_str(),
                 static_cast<int>(std::lround(job.progress() * 100)),
                 job.state() == v1::JOB_STATE_RUNNING ? job.stage().c_str() : StateName(job.state()));
    std::fflush(stderr);
    return;
  }
  // Plain lines: one per state or stage change, and per 10 % step.
  const std::string line = StrCat(StateName(job.state()), " ", job.stage(), " ",
                                  static_cast<int>(job.progress() * 10) * 10, "%");
  if (line != *last_line) {
    std::fprintf(stderr, "%s\n", line.c_str());
    *last_line = line;
  }
}

// Follows a job to its end; returns the final job through `out` and the exit code.
int Watch(const Options& o, const std::string& id, v1::Job* out) {
  auto stub = Connect(o);
  grpc::ClientContext ctx;
  v1::WatchJobRequest request;
  request.set_job_id(id);
  auto reader = stub->WatchJob(&ctx, request);
  v1::JobEvent event;
  const bool tty = !o.quiet && isatty(STDERR_FILENO);
  std::string last;
  bool ended = false;
  while (reader->Read(&event)) {
    *out = event.job();
    if (!o.quiet) PrintProgress(*out, tty, &last);
    if (Terminal(out->state())) ended = true;
  }
  if (tty) std::fprintf(stderr, "\n");
  const grpc::Status status = reader->Finish();
  if (!status.ok()) return FailRpc("watch", status);
  if (!ended) return Fail("the watch ended before the job finished");
  if (out->state() == v1::JOB_STATE_FAILED) return Fail(StrCat("job ", id, " failed: ", out->error()), kExitFailed);
  if (out->state() == v1::JOB_STATE_CANCELLED) {
    return Fail(StrCat("job ", id, " was cancelled: ", out->error()), kExitCancelled);
  }
  return 0;
}

int FetchBytes(const Options& o, const std::string& id, const std::string& name, std::string* bytes) {
  auto stub = Connect(o);
  grpc::ClientContext ctx;
  v1::FetchResultRequest request;
  request.set_job_id(id);
  request.set_name(name);
  auto reader = stub->FetchResult(&ctx, request);
  v1::ResultChunk chunk;
  while (reader->Read(&chunk)) *bytes += chunk.data();
  const grpc::Status status = reader->Finish();
  if (!status.ok()) return FailRpc("fetch", status);
  return 0;
}

// Writes a fetched Draco mesh to `path` in the format its extension names.
int WriteResult(const std::string& bytes, const std::string& path) {
  auto format = lsqsurf::io::FormatFromPath(path);
  if (!format.ok()) return Fail(std::string(format.status().message()));
  absl::Status s;
  if (*format == lsqsurf::io::FileFormat::kDraco) {
    s = lsqsurf::io::WriteFileAtomically(path, bytes);
  } else {
    auto mesh = lsqsurf::io::DecodeDracoMesh(bytes);
    if (!mesh.ok()) return Fail(StrCat("the result cannot be decoded: ", mesh.status().message()));
    s = lsqsurf::io::WriteMeshFile(path, *mesh);
  }
  if (!s.ok()) return Fail(std::string(s.message()));
  return 0;
}

void PrintJob(const v1::Job& job) {
  std::printf("id         %s\nmethod     %s\nstate      %s\n", job.id().c_str(), job.spec().method().c_str(),
              StateName(job.state()));
  if (job.state() == v1::JOB_STATE_RUNNING) {
    std::printf("progress   %.0f%% (%s)\n", job.progress() * 100, job.stage().c_str());
  }
  if (!job.error().empty()) std::printf("error      %s\n", job.error().c_str());
  std::printf("input      %lld points, %lld bytes\nattempts   %d\n", static_cast<long long>(job.input_points()),
              static_cast<long long>(job.input_bytes()), job.attempts());
  for (const auto& p : job.spec().parameters()) std::printf("param      %s=%g\n", p.first.c_str(), p.second);
  for (const auto& s : job.statistics()) std::printf("stat       %s=%g\n", s.name().c_str(), s.value());
  for (const auto& r : job.results()) std::printf("result     %s\n", r.c_str());
}

// Renders an artifact of a finished job into a PNG file.
int RenderToFile(const Options& o, const std::string& id, const std::string& name, const v1::RenderOptions& view,
                 const std::string& path) {
  v1::RenderRequest request;
  request.set_job_id(id);
  request.set_name(name);
  *request.mutable_options() = view;
  v1::RenderResponse response;
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::minutes(5));
  const grpc::Status status = Connect(o)->Render(&ctx, request, &response);
  if (!status.ok()) return FailRpc("render", status);
  if (absl::Status s = lsqsurf::io::WriteFileAtomically(path, response.png()); !s.ok()) return Fail(std::string(s.message()));
  if (!o.quiet) {
    std::fprintf(stderr, "wrote %s (%s", path.c_str(), response.renderer().c_str());
    if (!view.color().empty()) std::fprintf(stderr, "; %s from %g to %g", view.color().c_str(), response.color_min(), response.color_max());
    std::fprintf(stderr, ")\n");
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf: client of the lsqsurfd reconstruction server"};
  app.require_subcommand(1);
  Options o;
  const char* env = std::getenv("LSQSURF_SERVER");
  o.server = env && *env ? env : "127.0.0.1:50051";
  app.add_option("--server", o.server, "HOST:PORT of lsqsurfd (default: $LSQSURF_SERVER or 127.0.0.1:50051)");
  app.add_flag("-q,--quiet", o.quiet, "no progress output");
  auto add_job_options = [&](CLI::App* cmd) {
    cmd->add_option("--method", o.method, "surface method")->capture_default_str();
    cmd->add_option("--param", o.params, "method parameter as name=value (repeatable)");
    cmd->add_option("--mesh-bits", o.mesh_bits, "Draco quantization of result positions (8..30)");
  };

  std::string input, output, id, name, reference, candidate;
  int limit = 0;
  size_t samples = 1'000'000;

  auto* reconstruct = app.add_subcommand("reconstruct", "upload a cloud, wait, and write the mesh");
  reconstruct->add_option("input", input, "point cloud (.ply .obj .xyz .xyzn .drc)")->required();
  std::vector<std::string> outputs;
  reconstruct->add_option("-o,--output", outputs, "mesh to write (.ply .obj .drc); repeat for several")
      ->required();
  add_job_options(reconstruct);
  std::string preview;
  reconstruct->add_option("--preview", preview, "also render the mesh to this PNG file (view options below)");
  ViewFlags view;
  view.AddTo(reconstruct);
  auto* submit = app.add_subcommand("submit", "upload a cloud and print the job id");
  submit->add_option("input", input, "point cloud")->required();
  add_job_options(submit);
  bool job_preview = false;
  submit->add_flag("--job-preview", job_preview, "the job also draws preview.png into its results (view options below)");
  view.AddTo(submit);
  auto* watch = app.add_subcommand("watch", "follow a job until it ends");
  watch->add_option("id", id, "job id")->required();
  auto* status = app.add_subcommand("status", "show a job");
  status->add_option("id", id, "job id")->required();
  auto* list = app.add_subcommand("list", "list jobs, newest first");
  list->add_option("--limit", limit, "at most this many");
  auto* cancel = app.add_subcommand("cancel", "cancel a queued or running job");
  cancel->add_option("id", id, "job id")->required();
  auto* remove = app.add_subcommand("delete", "delete a finished job and its files");
  remove->add_option("id", id, "job id")->required();
  auto* fetch = app.add_subcommand("fetch", "download a result");
  fetch->add_option("id", id, "job id")->required();
  fetch->add_option("-o,--output", output, "file to write (.ply .obj .drc; other artifacts as they are)")->required();
  fetch->add_option("--name", name, "artifact name, e.g. preview.png or stats.csv (default: the mesh)");
  auto* methods = app.add_subcommand("methods", "list the server's methods and parameters");
  auto* track = app.add_subcommand("track", "advect an interface through a velocity field; write frames and stats");
  std::string interface = "sphere", field = "rotation";
  double period = 3, h = 1.0 / 128, dt = 1;
  int steps = 100, stride = 10;
  bool track_meshes = false;
  std::string resampling = "markers";
  track->add_option("--interface", interface, "zalesak | sphere | FILE (oriented cloud in the unit cube)")
      ->capture_default_str();
  track->add_option("--field", field,
                    "rotation (Zalesak) | deformation (Enright) | FILE (legacy VTK STRUCTURED_POINTS with VECTORS)")
      ->capture_default_str();
  track->add_option("--period", period, "period T of the deformation field")->capture_default_str();
  track->add_option("--h", h, "grid spacing; 1/h must be a whole number in 8..512")->capture_default_str();
  track->add_option("--dt", dt, "time step")->capture_default_str();
  track->add_option("--steps", steps, "number of steps")->capture_default_str();
  track->add_option("--stride", stride, "write a frame every this many steps")->capture_default_str();
  track->add_option("--resampling", resampling,
                    "markers (advected points kept, gaps filled; keeps thin sheets) | gridlines (the seed's "
                    "re-generation every step)")
      ->check(CLI::IsMember({"markers", "gridlines"}))
      ->capture_default_str();
  track->add_flag("--meshes", track_meshes, "also write a mesh of every frame and its volume (mesh_volume in stats.csv)");
  track->add_option("-o,--output", output, "folder for frame_NNNNN.drc, stats.csv and summary.txt")->required();
  bool pictures = false;
  double turntable = 0;
  auto* pictures_flag = track->add_flag("--pictures", pictures, "also draw every frame to frame_NNNNN.png (view options below)");
  track->add_option("--turntable", turntable, "with --pictures: degrees the camera turns from frame to frame")
      ->needs(pictures_flag);
  view.AddTo(track);
  auto* render = app.add_subcommand("render", "render a result (mesh, points or frame) to a PNG picture");
  render->add_option("id", id, "job id")->required();
  render->add_option("-o,--output", output, "PNG file to write")->required();
  render->add_option("--name", name, "artifact name (default: the job's first result)");
  view.AddTo(render);
  auto* compare = app.add_subcommand("compare", "Chamfer/Hausdorff distance and normal consistency");
  compare->add_option("reference", reference, "reference mesh")->required();
  compare->add_option("candidate", candidate, "candidate mesh")->required();
  compare->add_option("--samples", samples, "samples per surface")->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  if (*reconstruct || *submit) {
    if (o.method == "track") return Fail("'track' jobs write frames, not a mesh: use `lsqsurf track`");
    if (job_preview) {
      o.preview.emplace();
      *o.preview->mutable_options() = view.Options();
    }
    v1::Job job;
    if (int rc = Submit(o, input, &job); rc != 0) return rc;
    if (*submit) {
      std::printf("%s\n", job.id().c_str());
      return 0;
    }
    if (!o.quiet) std::fprintf(stderr, "job %s accepted (%lld points)\n", job.id().c_str(),
                               static_cast<long long>(job.input_points()));
    if (int rc = Watch(o, job.id(), &job); rc != 0) return rc;
    std::string bytes;
    if (int rc = FetchBytes(o, job.id(), "", &bytes); rc != 0) return rc;
    for (const auto& path : outputs) {
      if (int rc = WriteResult(bytes, path); rc != 0) return rc;
    }
    if (!o.quiet) {
      for (const auto& s : job.statistics()) std::fprintf(stderr, "  %s = %g\n", s.name().c_str(), s.value());
      for (const auto& path : outputs) std::fprintf(stderr, "wrote %s\n", path.c_str());
    }
    if (!preview.empty()) return RenderToFile(o, job.id(), "", view.Options(), preview);
    return 0;
  }
  if (*render) return RenderToFile(o, id, name, view.Options(), output);
  if (*watch) {
    v1::Job job;
    return Watch(o, id, &job);
  }
  if (*track) {
    const double cells = 1.0 / h;
    if (!(h > 0) || std::abs(cells - std::round(cells)) > 1e-6 * cells) {
      return Fail(StrCat("--h ", h, ": 1/h must be a whole number (e.g. 0.0078125 = 1/128)"));
    }
    const std::string upload = interface == "zalesak" || interface == "sphere" ? "" : interface;
    o.method = "track";
    o.params = {StrCat("interface=", interface == "sphere" ? 1 : interface == "zalesak" ? 2 : 0),
                StrCat("field=", field == "rotation" ? 0 : field == "deformation" ? 1 : 2), StrCat("period=", period),
                StrCat("cells=", std::lround(cells)), StrCat("dt=", dt), StrCat("steps=", steps),
                StrCat("stride=", stride), StrCat("meshes=", track_meshes ? 1 : 0),
                StrCat("resampling=", resampling == "markers" ? 1 : 0)};
    if (pictures) {
      o.preview.emplace();
      *o.preview->mutable_options() = view.Options();
      o.preview->set_turntable_deg_per_frame(turntable);
    }
    v1::Job job;
    const bool named_field = field == "rotation" || field == "deformation";
    if (int rc = Submit(o, upload, &job, named_field ? "" : field); rc != 0) return rc;
    if (!o.quiet) std::fprintf(stderr, "job %s accepted\n", job.id().c_str());
    if (int rc = Watch(o, job.id(), &job); rc != 0) return rc;
    std::error_code ec;
    std::filesystem::create_directories(output, ec);
    if (ec) return Fail(StrCat("cannot create ", output, ": ", ec.message()));
    for (const std::string& artifact : job.results()) {
      std::string bytes;
      if (int rc = FetchBytes(o, job.id(), artifact, &bytes); rc != 0) return rc;
      const std::string path = (std::filesystem::path(output) / artifact).string();
      if (absl::Status s = lsqsurf::io::WriteFileAtomically(path, bytes); !s.ok()) return Fail(std::string(s.message()));
    }
    if (!o.quiet) {
      for (const auto& s : job.statistics()) std::fprintf(stderr, "  %s = %g\n", s.name().c_str(), s.value());
      std::fprintf(stderr, "wrote %d files to %s\n", job.results_size(), output.c_str());
    }
    return 0;
  }
  auto stub = Connect(o);
  grpc::ClientContext ctx;
  if (*status) {
    v1::GetJobRequest request;
    request.set_job_id(id);
    v1::Job job;
    if (grpc::Status s = stub->GetJob(&ctx, request, &job); !s.ok()) return FailRpc("status", s);
    PrintJob(job);
    return 0;
  }
  if (*list) {
    v1::ListJobsRequest request;
    request.set_limit(limit);
    v1::ListJobsResponse response;
    if (grpc::Status s = stub->ListJobs(&ctx, request, &response); !s.ok()) return FailRpc("list", s);
    for (const auto& job : response.jobs()) {
      std::printf("%s  %-9s  %-7s  %3.0f%%  %s\n", job.id().c_str(), StateName(job.state()),
                  job.spec().method().c_str(), job.progress() * 100,
                  job.error().empty() ? job.stage().c_str() : job.error().c_str());
    }
    return 0;
  }
  if (*cancel) {
    v1::CancelJobRequest request;
    request.set_job_id(id);
    v1::Job job;
    if (grpc::Status s = stub->CancelJob(&ctx, request, &job); !s.ok()) return FailRpc("cancel", s);
    std::printf("%s %s\n", job.id().c_str(), StateName(job.state()));
    return 0;
  }
  if (*remove) {
    v1::DeleteJobRequest request;
    request.set_job_id(id);
    v1::DeleteJobResponse response;
    if (grpc::Status s = stub->DeleteJob(&ctx, request, &response); !s.ok()) return FailRpc("delete", s);
    return 0;
  }
  if (*fetch) {
    std::string bytes;
    if (int rc = FetchBytes(o, id, name, &bytes); rc != 0) return rc;
    // Meshes convert to the output's format; pictures, tables and text are written as they are.
    if (!name.empty() && !name.ends_with(".drc")) {
      if (absl::Status s = lsqsurf::io::WriteFileAtomically(output, bytes); !s.ok()) return Fail(std::string(s.message()));
      return 0;
    }
    return WriteResult(bytes, output);
  }
  if (*methods) {
    v1::ListMethodsResponse response;
    if (grpc::Status s = stub->ListMethods(&ctx, {}, &response); !s.ok()) return FailRpc("methods", s);
    for (const auto& m : response.methods()) {
      std::printf("%s: %s\n", m.name().c_str(), m.description().c_str());
      for (const auto& p : m.parameters()) {
        std::printf("  %-18s default %-8g range [%g, %g]%s  %s\n", p.name().c_str(), p.default_value(),
                    p.min_value(), p.max_value(), p.integer() ? " integer" : "", p.help().c_str());
      }
      std::string attributes;
      for (const auto& a : m.attributes()) attributes += (attributes.empty() ? "" : ", ") + a;
      if (!attributes.empty()) std::printf("  mesh attributes (--color): %s\n", attributes.c_str());
    }
    return 0;
  }
  if (*compare) {
    auto ref = lsqsurf::io::ReadMeshFile(reference);
    if (!ref.ok()) return Fail(std::string(ref.status().message()));
    auto cand = lsqsurf::io::ReadMeshFile(candidate);
    if (!cand.ok()) return Fail(std::string(cand.status().message()));
    lsqsurf::core::LocalJobContext local;
    lsqsurf::core::CompareParams params;
    params.samples = samples;
    auto r = lsqsurf::core::CompareMeshes(*ref, *cand, params, local);
    if (!r.ok()) return Fail(std::string(r.status().message()));
    std::printf("chamfer            %.4e\nhausdorff          %.4e\nnormal_consistency %.5f\n"
                "far_fraction       %.4e\ndiagonal           %.6g\n",
                r->chamfer, r->hausdorff, r->normal_consistency, r->far_fraction, r->diagonal);
    return 0;
  }
  return Fail("no command given");
}
