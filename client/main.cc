// lsqsurf — command-line client of lsqsurfd: upload clouds, follow jobs, download meshes, and
// compare meshes with the benchmark measures. Parses flags and calls the client library.
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <optional>

#include "client/client.h"
#include "worker/core/address.h"
#include "worker/core/sampling.h"
#include "worker/core/strings.h"
#include "worker/core/surface_distance.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace {

namespace v1 = lsqsurf::v1;
namespace client = lsqsurf::client;
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

int FailStatus(const char* what, const absl::Status& s) {
  const int code =
      s.code() == absl::StatusCode::kUnavailable || s.code() == absl::StatusCode::kAborted ? kExitLocal : kExitFailed;
  return Fail(StrCat(what, ": ", s.message(), " (", static_cast<int>(s.code()), ")"), code);
}

// View options shared by render, reconstruct --preview, submit --job-preview and track
// --pictures. Options left out are not sent: the server's defaults apply. Defaults and ranges
// are not repeated here: they are the tables' (docs/parameters.md, lsqsurf methods).
struct ViewFlags {
  std::optional<int> size, samples;
  std::optional<double> azimuth, elevation, distance, fov;
  std::optional<std::string> up, color;
  bool flat = false, wireframe = false, transparent = false;

  void AddTo(CLI::App* cmd) {
    cmd->add_option("--size", size, "picture width and height in pixels");
    cmd->add_option("--up", up, "axis pointing up in the picture: x, y or z (scans are often y)")
        ->check(CLI::IsMember({"x", "y", "z"}));
    cmd->add_option("--azimuth", azimuth, "camera degrees about the up axis");
    cmd->add_option("--elevation", elevation, "camera degrees above the plane normal to the up axis");
    cmd->add_option("--distance", distance, "camera distance from the box centre (unset: frame the model)");
    cmd->add_option("--fov", fov, "vertical field of view in degrees");
    cmd->add_option("--color", color, "per-vertex attribute to colour by, e.g. degree or depth (PU meshes)");
    cmd->add_flag("--flat", flat, "flat shading (one normal per triangle)");
    cmd->add_flag("--wireframe", wireframe, "draw the triangle edges");
    cmd->add_flag("--transparent", transparent, "transparent background");
    cmd->add_option("--samples", samples, "MSAA samples per pixel: 1, 2, 4 or 8");
  }

  v1::RenderOptions Options() const {
    v1::RenderOptions view;
    if (size) view.set_width(*size), view.set_height(*size);
    if (azimuth) view.set_azimuth_deg(*azimuth);
    if (elevation) view.set_elevation_deg(*elevation);
    if (distance) view.set_distance(*distance);
    if (fov) view.set_fov_deg(*fov);
    if (up)
      view.set_up_axis(*up == "x"   ? v1::RenderOptions::UP_AXIS_X
                       : *up == "y" ? v1::RenderOptions::UP_AXIS_Y
                                    : v1::RenderOptions::UP_AXIS_Z);
    if (color) view.set_color(*color);
    if (flat) view.set_flat_shading(true);
    if (wireframe) view.set_wireframe(true);
    if (transparent) view.set_transparent(true);
    if (samples) view.set_samples(*samples);
    return view;
  }
};

// render --volume: how a volume job's field is drawn. Options left out keep the server's defaults.
struct VolumeViewFlags {
  bool volume = false;
  std::optional<double> iso_ray, step;
  std::optional<int> resolution;
  std::string opacity, transfer;

  void AddTo(CLI::App* cmd) {
    cmd->add_flag("--volume", volume, "draw a volume job's field by direct volume rendering");
    cmd->add_option("--iso-ray", iso_ray, "draw the isosurface of this value by ray casting instead");
    cmd->add_option("--opacity", opacity, "opacity transfer function t:alpha,... (t over the colour range)");
    cmd->add_option("--transfer", transfer, "file with the opacity points, one 't alpha' or 't:alpha' per line");
    cmd->add_option("--resolution", resolution, "grid points along the longest side of the field's box");
    cmd->add_option("--step", step, "ray step in grid cells");
  }
  bool Requested() const { return volume || iso_ray || !opacity.empty() || !transfer.empty(); }
  absl::Status Apply(v1::RenderOptions* view) const {
    std::string points = opacity;
    if (!transfer.empty()) {
      auto text = lsqsurf::io::ReadFileBytes(transfer);
      if (!text.ok()) return text.status();
      points.clear();
      std::string line;
      for (char c : *text + "\n") {
        if (c != '\n') {
          line += c == ' ' || c == '\t' ? ':' : c;
          continue;
        }
        while (!line.empty() && (line.back() == ':' || line.back() == '\r')) line.pop_back();
        if (!line.empty() && line[0] != '#') points += (points.empty() ? "" : ",") + line;
        line.clear();
      }
    }
    if (!points.empty()) view->set_opacity(points);
    if (iso_ray) {
      view->set_volume_mode(v1::RenderOptions::VOLUME_MODE_ISOSURFACE);
      view->set_iso_value(*iso_ray);
    }
    if (resolution) view->set_volume_resolution(*resolution);
    if (step) view->set_ray_step(*step);
    return absl::OkStatus();
  }
};

// How to reach the server: TLS, and the token. Flags win over LSQSURF_* variables.
struct ConnectionFlags {
  std::string ca, cert, key, server_name, token_file;
  bool tls = false, plaintext = false;

  void AddTo(CLI::App& app) {
    app.add_option("--tls-ca", ca,
                   "PEM certificates to trust for the server's ($LSQSURF_TLS_CA; default: the system's)");
    app.add_option("--tls-cert", cert, "PEM client certificate, for mutual TLS ($LSQSURF_TLS_CERT)");
    app.add_option("--tls-key", key, "PEM private key of --tls-cert ($LSQSURF_TLS_KEY)");
    app.add_option("--tls-server-name", server_name,
                   "name the server's certificate must carry, when not the address's host ($LSQSURF_TLS_SERVER_NAME)");
    app.add_flag("--tls", tls, "use TLS with the system's roots (implied by --tls-*, and for non-loopback servers)");
    app.add_flag("--plaintext", plaintext, "talk to a non-loopback server without TLS");
    app.add_option("--token-file", token_file,
                   "file holding the token for a server with tokens (default: $LSQSURF_TOKEN)");
  }

  // The options for `server`: TLS when asked for or when the server is not on loopback (unless
  // --plaintext). Errors: kInvalidArgument (an unreadable file, --plaintext with --tls-*).
  absl::StatusOr<client::ConnectOptions> Resolve(const std::string& server) {
    const auto from_env = [](std::string& value, const char* name) {
      const char* env = std::getenv(name);
      if (value.empty() && env != nullptr) value = env;
    };
    from_env(ca, "LSQSURF_TLS_CA");
    from_env(cert, "LSQSURF_TLS_CERT");
    from_env(key, "LSQSURF_TLS_KEY");
    from_env(server_name, "LSQSURF_TLS_SERVER_NAME");
    client::ConnectOptions options;
    options.server_name = server_name;
    for (auto [path, pem] : {std::pair{&ca, &options.ca_pem}, {&cert, &options.cert_pem}, {&key, &options.key_pem}}) {
      if (path->empty()) continue;
      auto bytes = lsqsurf::io::ReadFileBytes(*path);
      if (!bytes.ok()) return bytes.status();
      *pem = *std::move(bytes);
    }
    if (options.cert_pem.empty() != options.key_pem.empty()) {
      return absl::InvalidArgumentError("--tls-cert and --tls-key go together");
    }
    if (plaintext && (tls || options.uses_tls())) return absl::InvalidArgumentError("--plaintext contradicts --tls*");
    options.tls = tls || (!plaintext && !lsqsurf::core::IsLoopback(server));
    if (!token_file.empty()) {
      auto token = lsqsurf::io::ReadFileBytes(token_file);
      if (!token.ok()) return token.status();
      options.token = *std::move(token);
    } else if (const char* env = std::getenv("LSQSURF_TOKEN"); env != nullptr) {
      options.token = env;
    }
    while (!options.token.empty() && std::isspace(static_cast<unsigned char>(options.token.back()))) {
      options.token.pop_back();
    }
    if (!options.token.empty()) {
      if (absl::Status s = client::CheckToken(options.token); !s.ok()) return s;
    }
    return options;
  }
};

struct Globals {
  std::string server;
  bool quiet = false;
  ConnectionFlags connection;
  client::ConnectOptions connect;  // From `connection`, once parsed.

  void AddTo(CLI::App& app) {
    const char* env = std::getenv("LSQSURF_SERVER");
    server = env && *env ? env : "127.0.0.1:50051";
    app.add_option("--server", server, "HOST:PORT of lsqsurfd (default: $LSQSURF_SERVER or 127.0.0.1:50051)");
    app.add_flag("-q,--quiet", quiet, "no progress output");
    connection.AddTo(app);
  }
  absl::Status Resolve() {
    auto resolved = connection.Resolve(server);
    if (!resolved.ok()) return resolved.status();
    connect = *std::move(resolved);
    return absl::OkStatus();
  }
};

client::Client Connect(const Globals& g) { return client::Client(g.server, g.connect); }

// What reconstruct and submit upload.
struct JobFlags {
  std::string method = "iamls";
  std::vector<std::string> params;
  int mesh_bits = 0;

  void AddTo(CLI::App* cmd) {
    cmd->add_option("--method", method, "iamls | pu | ramls | apss | aamls | imls | volume (lsqsurf methods)")
        ->capture_default_str();
    cmd->add_option("--param", params, "method parameter as name=value (repeatable; lsqsurf methods lists them)");
    cmd->add_option("--mesh-bits", mesh_bits, "Draco quantization of result positions (8..30; default: per mesh)");
  }

  absl::StatusOr<v1::JobSpec> Spec() const {
    if (method == "track")
      return absl::InvalidArgumentError("'track' jobs write frames, not a mesh: use `lsqsurf track`");
    v1::JobSpec spec;
    if (absl::Status s = client::SetMethod(&spec, method); !s.ok()) return s;
    for (const auto& p : params) {
      if (absl::Status s = client::SetParamAssignment(&spec, p); !s.ok()) return s;
    }
    spec.set_mesh_position_bits(mesh_bits);
    return spec;
  }
};

// The Draco bytes of a cloud file: .drc as it is, other formats read and encoded with unit normals.
absl::StatusOr<std::string> CloudBytes(const std::string& path) {
  if (path.empty()) return std::string();
  if (lsqsurf::io::FormatFromPath(path).value_or(lsqsurf::io::FileFormat::kPly) == lsqsurf::io::FileFormat::kDraco) {
    return lsqsurf::io::ReadFileBytes(path);
  }
  auto cloud = lsqsurf::io::ReadPointCloudFile(path);
  if (!cloud.ok()) return cloud.status();
  // The server takes unit normals; files often carry unnormalized ones.
  for (auto& n : cloud->normals) {
    if (n.norm() > 0) n.normalize();
  }
  auto encoded = lsqsurf::io::EncodeDracoPointCloud(*cloud, {});
  if (!encoded.ok()) return absl::InvalidArgumentError(StrCat(path, ": ", encoded.status().message()));
  return encoded;
}

class ProgressPrinter {
 public:
  explicit ProgressPrinter(bool quiet) : quiet_(quiet), tty_(!quiet && isatty(STDERR_FILENO)) {}
  ~ProgressPrinter() {
    if (tty_ && printed_) std::fprintf(stderr, "\n");
  }
  void operator()(const v1::Job& job) {
    if (quiet_) return;
    printed_ = true;
    if (tty_) {
      const int width = 30;
      const int filled = static_cast<int>(std::lround(job.progress() * width));
      std::fprintf(stderr, "\r[%s%s] %3d%% %-28s", std::string(static_cast<size_t>(filled), '#').c_str(),
                   std::string(static_cast<size_t>(width - filled), '.').c_str(),
                   static_cast<int>(std::lround(job.progress() * 100)),
                   job.state() == v1::JOB_STATE_RUNNING ? job.stage().c_str() : client::StateName(job.state()));
      std::fflush(stderr);
      return;
    }
    // Plain lines: one per state or stage change, and per 10 % step.
    const std::string line =
        StrCat(client::StateName(job.state()), " ", job.stage(), " ", static_cast<int>(job.progress() * 10) * 10, "%");
    if (line != last_) std::fprintf(stderr, "%s\n", line.c_str());
    last_ = line;
  }

 private:
  bool quiet_, tty_, printed_ = false;
  std::string last_;
};

// Follows a job to its end; returns the exit code and the final job through `out`.
int Watch(const Globals& g, const std::string& id, v1::Job* out) {
  client::Client c = Connect(g);
  absl::StatusOr<v1::Job> job;
  {
    ProgressPrinter progress(g.quiet);
    job = c.Watch(id, std::ref(progress));
  }
  if (!job.ok()) return FailStatus("watch", job.status());
  *out = *job;
  if (job->state() == v1::JOB_STATE_FAILED) return Fail(StrCat("job ", id, " failed: ", job->error()), kExitFailed);
  if (job->state() == v1::JOB_STATE_CANCELLED) {
    return Fail(StrCat("job ", id, " was cancelled: ", job->error()), kExitCancelled);
  }
  return 0;
}

// Writes a fetched artifact to `path`: Draco meshes convert to the extension's format;
// pictures, tables and text are written as they are.
int WriteResult(const std::string& bytes, const std::string& name, const std::string& path) {
  absl::Status s;
  auto format = lsqsurf::io::FormatFromPath(path);
  if ((!name.empty() && !name.ends_with(".drc")) || (format.ok() && *format == lsqsurf::io::FileFormat::kDraco)) {
    s = lsqsurf::io::WriteFileAtomically(path, bytes);
  } else if (!format.ok()) {
    return Fail(std::string(format.status().message()));
  } else {
    auto mesh = lsqsurf::io::DecodeDracoMesh(bytes);
    if (!mesh.ok()) return Fail(StrCat("the result cannot be decoded: ", mesh.status().message()));
    s = lsqsurf::io::WriteMeshFile(path, *mesh);
  }
  if (!s.ok()) return Fail(std::string(s.message()));
  return 0;
}

void PrintStatistics(const v1::Job& job) {
  for (const auto& s : job.statistics()) std::fprintf(stderr, "  %s = %g\n", s.name().c_str(), s.value());
}

void PrintJob(const v1::Job& job) {
  std::printf("id         %s\nmethod     %s\nstate      %s\n", job.id().c_str(), client::MethodOf(job.spec()).c_str(),
              client::StateName(job.state()));
  if (job.state() == v1::JOB_STATE_RUNNING)
    std::printf("progress   %.0f%% (%s)\n", job.progress() * 100, job.stage().c_str());
  if (!job.error().empty()) std::printf("error      %s\n", job.error().c_str());
  std::printf("input      %lld points, %lld bytes\nattempts   %d\n", static_cast<long long>(job.input_points()),
              static_cast<long long>(job.input_bytes()), job.attempts());
  if (!job.runner().empty()) std::printf("runner     %s\n", job.runner().c_str());
  if (!job.owner().empty()) std::printf("owner      %s\n", job.owner().c_str());
  // The parameters as run, in the text form --param takes.
  const auto& spec = job.spec();
  if (const auto* f =
          spec.GetReflection()->GetOneofFieldDescriptor(spec, v1::JobSpec::descriptor()->FindOneofByName("method"))) {
    std::string text = spec.GetReflection()->GetMessage(spec, f).ShortDebugString();
    std::printf("params     %s\n", text.c_str());
  }
  for (const auto& s : job.statistics()) std::printf("stat       %s=%g\n", s.name().c_str(), s.value());
  for (const auto& r : job.results()) std::printf("result     %s\n", r.c_str());
}

// The result that keeps a volume job's field (drawn by `render --volume`).
constexpr char kVolumeField[] = "field.lqvf";

int RenderToFile(const Globals& g, const std::string& id, const std::string& name, const v1::RenderOptions& view,
                 const std::string& path) {
  const auto start = std::chrono::steady_clock::now();
  auto response = Connect(g).Render(id, name, view);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (!response.ok()) return FailStatus("render", response.status());
  if (absl::Status s = lsqsurf::io::WriteFileAtomically(path, response->png()); !s.ok())
    return Fail(std::string(s.message()));
  if (!g.quiet) {
    std::fprintf(stderr, "wrote %s in %.2f s (%s", path.c_str(), seconds, response->renderer().c_str());
    if (!view.color().empty() || name == kVolumeField) {
      std::fprintf(stderr, "; %s from %g to %g", view.color().empty() ? "values" : view.color().c_str(),
                   response->color_min(), response->color_max());
    }
    if (name == kVolumeField) {
      std::fprintf(stderr, "; sampled grid error RMS %.3g, max %.3g", response->grid_rms_error(),
                   response->grid_max_error());
    }
    std::fprintf(stderr, ")\n");
  }
  return 0;
}

// What a job uploads: a cloud, or (method volume) a volume's vertices and cells.
struct Upload {
  std::string input, cells;
};

// Volume inputs: which fields travel and how a raw file is laid out.
struct VolumeFlags {
  std::string field, color_by, raw;

  void AddTo(CLI::App* cmd) {
    cmd->add_option("--field", field, "method volume: the scalar field to reconstruct");
    cmd->add_option("--color-by", color_by, "method volume: a second field sampled on the isosurface");
    cmd->add_option("--raw", raw, "method volume: read the input as a raw volume NXxNYxNZ:TYPE[:SPACING]");
  }
  // Sets the field parameters of a volume spec and encodes the file.
  absl::StatusOr<Upload> Encode(const std::string& path, v1::JobSpec* spec) const {
    if (field.empty()) return absl::InvalidArgumentError("method volume needs --field NAME");
    std::vector<std::string> fields = {field};
    spec->mutable_volume()->set_field(field);
    if (!color_by.empty()) {
      spec->mutable_volume()->set_color_by(color_by);
      if (color_by != field) fields.push_back(color_by);
    }
    auto encoded = client::EncodeVolumeFile(path, raw, fields);
    if (!encoded.ok()) return encoded.status();
    return Upload{std::move(encoded->vertices), std::move(encoded->cells)};
  }
};

// reconstruct, submit and volume.
struct SurfaceCommand {
  std::string input;
  std::vector<std::string> outputs;
  std::string preview;
  bool job_preview = false;
  JobFlags job;
  ViewFlags view;
  VolumeFlags volume;
  std::vector<double> iso;
  std::string csg_expression;  // Method csg: the solid (no upload).
  struct EditFlags {
    std::string source, ball, set, refit;
    bool remove = false;
  } edit;  // Method edit.

  // Fills EditParams from `lsqsurf edit ID --ball x,y,z,r --set degree=N | --refit error_threshold=E | --remove`.
  absl::Status ApplyEdit(v1::JobSpec* spec) const {
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

  int Run(const Globals& g, bool wait) const {
    auto spec = job.Spec();
    if (!spec.ok()) return Fail(std::string(spec.status().message()));
    if (job.method == "csg") spec->mutable_csg()->set_expression(csg_expression);
    if (job.method == "edit") {
      if (absl::Status s = ApplyEdit(&*spec); !s.ok()) return Fail(std::string(s.message()));
    }
    if (job_preview) *spec->mutable_preview()->mutable_options() = view.Options();
    absl::StatusOr<Upload> upload = absl::UnknownError("");
    if (job.method == "volume") {
      if (!iso.empty()) {
        std::string text;
        for (double v : iso) text += StrCat(text.empty() ? "" : ",", v);
        spec->mutable_volume()->set_iso(text);
      }
      upload = volume.Encode(input, &*spec);
    } else {
      auto bytes = CloudBytes(input);
      if (bytes.ok()) upload = Upload{*std::move(bytes), {}};
      if (!bytes.ok()) upload = bytes.status();
    }
    if (!upload.ok()) return Fail(std::string(upload.status().message()));
    client::Client c = Connect(g);
    auto accepted = c.Submit(*spec, upload->input, {}, upload->cells);
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
      if (!g.quiet) PrintStatistics(done);
      std::printf("%s\n", done.id().c_str());
      return 0;
    }
    auto mesh = c.Fetch(done.id(), "");
    if (!mesh.ok()) return FailStatus("fetch", mesh.status());
    for (const auto& path : outputs) {
      if (int rc = WriteResult(*mesh, "", path); rc != 0) return rc;
    }
    if (!g.quiet) {
      PrintStatistics(done);
      for (const auto& path : outputs) std::fprintf(stderr, "wrote %s\n", path.c_str());
    }
    if (!preview.empty()) return RenderToFile(g, done.id(), "", view.Options(), preview);
    return 0;
  }
};

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

// probe: values of a finished volume job at points of an XYZ file, or on a grid.
struct ProbeCommand {
  std::string id, points, grid, field, output;

  void AddTo(CLI::App* probe) {
    probe->add_option("id", id, "id of a succeeded volume job")->required();
    probe->add_option("points", points, "points to probe: an XYZ text file, one 'x y z' per line");
    probe->add_option("--grid", grid, "resample on a grid NXxNYxNZ over the field's box instead (writes .vti)");
    probe->add_option("--field", field, "the field to probe (default: the job's first)");
    probe->add_option("-o,--output", output, "values.csv (points) or field.vti (grid)")->required();
  }

  int Run(const Globals& g) const {
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
      PrintStatistics(done);
      std::fprintf(stderr, "wrote %s\n", output.c_str());
    }
    return 0;
  }
};

// track: every option the user leaves out keeps the server's default.
struct TrackCommand {
  std::string interface, field, modulation, resampling, output;
  std::optional<double> period, h, dt, merge_distance, support, marker_spacing, marker_gap, regeneration_stretch;
  std::optional<int> steps, stride;
  std::optional<int64_t> max_points;
  bool meshes = false, pictures = false;
  double turntable = 0;
  ViewFlags view;

  void AddTo(CLI::App* track) {
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

  absl::StatusOr<v1::JobSpec> Spec() const {
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
      p.set_modulation(modulation == "reversal" ? v1::TrackParams::MODULATION_REVERSAL
                                                : v1::TrackParams::MODULATION_COS);
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

  int Run(const Globals& g) const {
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
      if (absl::Status s = lsqsurf::io::WriteFileAtomically(path, *bytes); !s.ok())
        return Fail(std::string(s.message()));
    }
    if (!g.quiet) {
      PrintStatistics(done);
      std::fprintf(stderr, "wrote %d files to %s\n", done.results_size(), output.c_str());
    }
    return 0;
  }
};

int PrintMethods(const Globals& g) {
  auto response = Connect(g).ListMethods();
  if (!response.ok()) return FailStatus("methods", response.status());
  for (const auto& m : response->methods()) {
    std::printf("%s: %s\n", m.name().c_str(), m.description().c_str());
    for (const auto& p : m.parameters()) {
      std::string range;
      if (p.type() == v1::Parameter::TYPE_CHOICE) {
        for (const auto& c : p.choices()) range += (range.empty() ? "" : " | ") + c.name();
      } else if (p.type() == v1::Parameter::TYPE_FLAG) {
        range = "true | false";
      } else {
        range = StrCat("[", p.min_value(), ", ", p.max_value(), "]", p.unit().empty() ? "" : " ", p.unit());
      }
      const std::string def = p.type() == v1::Parameter::TYPE_CHOICE ? p.default_choice()
                              : p.type() == v1::Parameter::TYPE_FLAG ? (p.default_value() != 0 ? "true" : "false")
                                                                     : StrCat(p.default_value());
      std::printf("  %-18s default %-9s %s  %s\n", p.name().c_str(), def.c_str(), range.c_str(), p.help().c_str());
    }
    std::string attributes;
    for (const auto& a : m.attributes()) attributes += (attributes.empty() ? "" : ", ") + a;
    if (!attributes.empty()) std::printf("  mesh attributes (--color): %s\n", attributes.c_str());
  }
  return 0;
}

// `lsqsurf health`: exit 0 when the server answers SERVING (what a container's HEALTHCHECK and a
// readiness probe run), 1 when it answers NOT_SERVING, 3 when nothing answers.
struct HealthCommand {
  std::string service;
  double timeout_seconds = 5;

  CLI::App* AddTo(CLI::App& app) {
    CLI::App* health = app.add_subcommand("health", "exit 0 when the server answers SERVING to a gRPC health check");
    health->add_option("--service", service, "service to ask about (default: the whole server)");
    health->add_option("--timeout", timeout_seconds, "seconds to wait for an answer")->capture_default_str();
    return health;
  }
  int Run(const Globals& g) const {
    const auto timeout = std::chrono::milliseconds(static_cast<int64_t>(timeout_seconds * 1000));
    auto serving = Connect(g).Serving(service, timeout);
    if (!serving.ok()) return FailStatus("health", serving.status());
    std::printf("%s\n", *serving ? "SERVING" : "NOT_SERVING");
    return *serving ? 0 : 1;
  }
};

int PrintServerInfo(const Globals& g) {
  auto info = Connect(g).GetServerInfo();
  if (!info.ok()) return FailStatus("info", info.status());
  std::printf(
      "version          %s\nmax_points       %lld\nmin_points       %lld\nmax_upload_bytes %lld\n"
      "max_queue        %d\nworkers          %d\nmax_renders      %d\ncan_render       %s\n"
      "max_job_memory   %lld\n",
      info->version().c_str(), static_cast<long long>(info->max_points()), static_cast<long long>(info->min_points()),
      static_cast<long long>(info->max_upload_bytes()), info->max_queue(), info->workers(), info->max_renders(),
      info->can_render() ? "yes" : "no", static_cast<long long>(info->max_job_memory_bytes()));
  if (!info->requires_token()) return 0;
  const v1::Account& a = info->account();
  const auto limit = [](int64_t value) { return value > 0 ? std::to_string(value) : std::string("none"); };
  std::printf(
      "account          %s (%s)\njobs             %d of %s\nstored_bytes     %lld of %s\n"
      "max_upload_bytes %s\n",
      a.name().c_str(), a.admin() ? "admin" : "user", a.active_jobs(), limit(a.max_jobs()).c_str(),
      static_cast<long long>(a.stored_bytes()), limit(a.max_stored_bytes()).c_str(),
      limit(a.max_upload_bytes()).c_str());
  return 0;
}

int Compare(const std::string& reference, const std::string& candidate, size_t samples) {
  auto ref = lsqsurf::io::ReadMeshFile(reference);
  if (!ref.ok()) return Fail(std::string(ref.status().message()));
  auto cand = lsqsurf::io::ReadMeshFile(candidate);
  if (!cand.ok()) return Fail(std::string(cand.status().message()));
  lsqsurf::core::LocalJobContext local;
  lsqsurf::core::CompareParams params;
  params.samples = samples;
  auto r = lsqsurf::core::CompareMeshes(*ref, *cand, params, local);
  if (!r.ok()) return Fail(std::string(r.status().message()));
  std::printf(
      "chamfer            %.4e\nhausdorff          %.4e\nnormal_consistency %.5f\n"
      "far_fraction       %.4e\ndiagonal           %.6g\n",
      r->chamfer, r->hausdorff, r->normal_consistency, r->far_fraction, r->diagonal);
  return 0;
}

// A cloud sampled from a mesh (area-uniform, normals interpolated from the vertex normals, as
// the benchmark samples), with optional Gaussian noise along the normal as a share of the mesh's
// bounding-box diagonal: test input with a known truth.
struct SampleCommand {
  std::string mesh_path, output;
  size_t points = 100'000;
  double noise = 0;
  uint64_t seed = 1234;

  CLI::App* AddTo(CLI::App& app) {
    CLI::App* sample =
        app.add_subcommand("sample", "sample a cloud with normals from a mesh (test input with a known truth)");
    sample->add_option("mesh", mesh_path, "mesh to sample (PLY, OBJ, DRC)")->required();
    sample->add_option("-o,--output", output, "cloud to write (PLY, XYZ, DRC)")->required();
    sample->add_option("--points", points, "number of points")->capture_default_str();
    sample->add_option("--noise", noise, "Gaussian noise along the normal, share of the diagonal")
        ->capture_default_str();
    sample->add_option("--seed", seed, "random seed")->capture_default_str();
    return sample;
  }
  int Run() const {
    auto mesh = lsqsurf::io::ReadMeshFile(mesh_path);
    if (!mesh.ok()) return Fail(std::string(mesh.status().message()));
    if (mesh->faces.empty()) return Fail(mesh_path + " has no triangles to sample");
    if (!(noise >= 0 && noise <= 0.1)) return Fail("--noise must be within [0, 0.1] (a share of the diagonal)");
    const double diagonal = lsqsurf::core::Diagonal(lsqsurf::core::BoundingBox(mesh->vertices));
    const lsqsurf::core::PointCloud cloud = lsqsurf::core::SampleCloud(*mesh, points, seed, noise * diagonal);
    if (absl::Status s = lsqsurf::io::WritePointCloudFile(output, cloud); !s.ok())
      return Fail(std::string(s.message()));
    return 0;
  }
};

// The commands that take a job id and print little.
int JobCommand(const Globals& g, const std::string& command, const std::string& id) {
  client::Client c = Connect(g);
  if (command == "status") {
    auto job = c.Get(id);
    if (!job.ok()) return FailStatus("status", job.status());
    PrintJob(*job);
    return 0;
  }
  if (command == "cancel") {
    auto job = c.Cancel(id);
    if (!job.ok()) return FailStatus("cancel", job.status());
    std::printf("%s %s\n", job->id().c_str(), client::StateName(job->state()));
    return 0;
  }
  if (command == "delete") {
    if (absl::Status s = c.Delete(id); !s.ok()) return FailStatus("delete", s);
    return 0;
  }
  v1::Job job;
  return Watch(g, id, &job);
}

int List(const Globals& g, int limit) {
  auto response = Connect(g).List(limit);
  if (!response.ok()) return FailStatus("list", response.status());
  for (const auto& job : response->jobs()) {
    std::printf("%s  %-9s  %-7s  %3.0f%%  %s\n", job.id().c_str(), client::StateName(job.state()),
                client::MethodOf(job.spec()).c_str(), job.progress() * 100,
                job.error().empty() ? job.stage().c_str() : job.error().c_str());
  }
  return 0;
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
  reconstruct->add_option("input", surface.input, "point cloud (.ply .obj .xyz .xyzn .drc)")->required();
  reconstruct->add_option("-o,--output", surface.outputs, "mesh to write (.ply .obj .drc); repeat for several")
      ->required();
  surface.job.AddTo(reconstruct);
  reconstruct->add_option("--preview", surface.preview, "also render the mesh to this PNG file (view options below)");
  surface.view.AddTo(reconstruct);
  auto* submit = app.add_subcommand("submit", "upload a cloud and print the job id");
  submit->add_option("input", surface.input, "point cloud")->required();
  surface.job.AddTo(submit);
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
  fetch->add_option("-o,--output", output, "file to write (.ply .obj .drc; other artifacts as they are)")->required();
  fetch->add_option("--name", name, "artifact name, e.g. preview.png or stats.csv (default: the mesh)");
  auto* methods = app.add_subcommand("methods", "list the server's methods and parameters");
  auto* info = app.add_subcommand("info", "show the server's version and limits");
  HealthCommand health_command;
  CLI::App* health = health_command.AddTo(app);
  TrackCommand track_command;
  auto* track = app.add_subcommand("track", "advect an interface through a velocity field; write frames and stats");
  track_command.AddTo(track);
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
  if (*render) {
    v1::RenderOptions options = render_view.Options();
    if (volume_view.Requested()) {
      if (absl::Status s = volume_view.Apply(&options); !s.ok()) return Fail(std::string(s.message()));
      name = kVolumeField;
    }
    return RenderToFile(g, id, name, options, output);
  }
  for (CLI::App* command : id_commands) {
    if (*command) return JobCommand(g, command->get_name(), id);
  }
  if (*list) return List(g, limit);
  if (*fetch) {
    auto bytes = Connect(g).Fetch(id, name);
    if (!bytes.ok()) return FailStatus("fetch", bytes.status());
    return WriteResult(*bytes, name, output);
  }
  if (*methods) return PrintMethods(g);
  if (*info) return PrintServerInfo(g);
  if (*health) return health_command.Run(g);
  if (*compare) return Compare(reference, candidate, samples);
  return Fail("no command given");
}
