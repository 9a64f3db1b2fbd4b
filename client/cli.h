// client/cli.h — the command-line client's flags and commands (what main.cc wires to CLI11).
// Each command family has a file: cli_common.cc (connection, progress, writing results),
// surface_commands.cc (reconstruct, submit, volume, csg, edit, probe), track_command.cc and
// info_commands.cc (methods, info, health, compare, sample, status, list).
#pragma once

#include <CLI/CLI.hpp>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "client/client.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

namespace v1 = lsqsurf::v1;
namespace client = lsqsurf::client;
using lsqsurf::core::StrCat;

// Exit codes: 0 success; 1 the job failed or the server refused the request; 2 the job was
// cancelled; 3 a local problem (bad file, unreachable server, usage).
constexpr int kExitFailed = 1;
constexpr int kExitCancelled = 2;
constexpr int kExitLocal = 3;

// Prints "lsqsurf: message" to stderr and returns `code`.
int Fail(const std::string& message, int code = kExitLocal);
// A request's failure: code kExitLocal when the server could not be reached, else kExitFailed.
int FailStatus(const char* what, const absl::Status& s);

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

  void AddTo(CLI::App& app);

  // The options for `server`: TLS when asked for or when the server is not on loopback (unless
  // --plaintext). Errors: kInvalidArgument (an unreadable file, --plaintext with --tls-*).
  absl::StatusOr<client::ConnectOptions> Resolve(const std::string& server);
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

client::Client Connect(const Globals& g);

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
absl::StatusOr<std::string> CloudBytes(const std::string& path);

// Follows a job to its end; returns the exit code and the final job through `out`.
int Watch(const Globals& g, const std::string& id, v1::Job* out);

// Writes a fetched artifact to `path`: Draco meshes convert to the extension's format;
// pictures, tables and text are written as they are.
int WriteResult(const std::string& bytes, const std::string& name, const std::string& path);

void PrintStatistics(const v1::Job& job);
void PrintJob(const v1::Job& job);

// The result that keeps a volume job's field (drawn by `render --volume`).
inline constexpr char kVolumeField[] = "field.lqvf";

int RenderToFile(const Globals& g, const std::string& id, const std::string& name, const v1::RenderOptions& view,
                 const std::string& path);

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
  absl::Status ApplyEdit(v1::JobSpec* spec) const;

  int Run(const Globals& g, bool wait) const;
};

// csg: a solid from an expression, run through the surface command's upload-free path.
CLI::App* AddCsgCommand(CLI::App& app, SurfaceCommand& surface);
// edit: a local edit of a kept PU function, as a new result.
CLI::App* AddEditCommand(CLI::App& app, SurfaceCommand& surface);

// probe: values of a finished volume job at points of an XYZ file, or on a grid.
struct ProbeCommand {
  std::string id, points, grid, field, output;

  void AddTo(CLI::App* probe);

  int Run(const Globals& g) const;
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

  void AddTo(CLI::App* track);

  absl::StatusOr<v1::JobSpec> Spec() const;

  int Run(const Globals& g) const;
};

int PrintMethods(const Globals& g);
int PrintServerInfo(const Globals& g);
int Compare(const std::string& reference, const std::string& candidate, size_t samples);
// The commands that take a job id and print little: status, cancel, delete, watch.
int JobCommand(const Globals& g, const std::string& command, const std::string& id);
int List(const Globals& g, int limit);

// `lsqsurf health`: exit 0 when the server answers SERVING (what a container's HEALTHCHECK and a
// readiness probe run), 1 when it answers NOT_SERVING, 3 when nothing answers.
struct HealthCommand {
  std::string service;
  double timeout_seconds = 5;

  CLI::App* AddTo(CLI::App& app);
  int Run(const Globals& g) const;
};

// A cloud sampled from a mesh (area-uniform, normals interpolated from the vertex normals, as
// the benchmark samples), with optional Gaussian noise along the normal as a share of the mesh's
// bounding-box diagonal: test input with a known truth.
struct SampleCommand {
  std::string mesh_path, output;
  size_t points = 100'000;
  double noise = 0;
  uint64_t seed = 1234;

  CLI::App* AddTo(CLI::App& app);
  int Run() const;
};

}  // namespace lsqsurf::cli
