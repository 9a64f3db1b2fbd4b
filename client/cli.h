// client/cli.h — the command-line client's flags and commands (what main.cc wires to CLI11).
// Each command family has a file: cli_common.cc (connection, progress, writing results),
// surface_commands.cc (reconstruct, submit, volume, csg, edit, probe), track_command.cc and
// info_commands.cc (methods, info, health, compare, sample, status, list).
#pragma once

#include <CLI/CLI.hpp>
#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "client/client.h"
#include "client/generated_flags.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

namespace v1 = lsqsurf::v1;
namespace client = lsqsurf::client;
using lsqsurf::core::StrAppend;
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
// --pictures: generated from RenderOptions and the view table. Options left out are not sent:
// the server's defaults apply.
struct ViewFlags {
  std::optional<int> size;
  GeneratedFlags fields{"view", *v1::RenderOptions::descriptor()};

  void AddTo(CLI::App* cmd);
  // Errors: kInvalidArgument naming a flag whose value has the wrong type.
  absl::StatusOr<v1::RenderOptions> Options() const;
};

// render --volume: how a volume job's field is drawn. Options left out keep the server's defaults.
struct VolumeViewFlags {
  bool volume = false;
  std::optional<double> iso_ray;
  std::string opacity, transfer;
  GeneratedFlags fields{"view", *v1::RenderOptions::descriptor()};

  void AddTo(CLI::App* cmd);
  bool Requested() const { return volume || iso_ray || !opacity.empty() || !transfer.empty() || !fields.empty(); }
  absl::Status Apply(v1::RenderOptions* view) const;
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
  bool all_statistics = false;  // --stats on the commands that wait for a job.
  ConnectionFlags connection;
  client::ConnectOptions connect;  // From `connection`, once parsed.

  void AddTo(CLI::App& app) {
    const char* env = std::getenv("LSQSURF_SERVER");
    server = env && *env ? env : "127.0.0.1:50051";
    app.add_option("--server", server, "HOST:PORT of lsqsurfd (default: $LSQSURF_SERVER or 127.0.0.1:50051)");
    app.add_flag("-q,--quiet", quiet, "no progress output");
    connection.AddTo(app);
  }
  // --stats on a command that waits for its job.
  void AddStatsFlag(CLI::App* command) {
    command->add_flag("--stats", all_statistics, "print every statistic of the finished job, not a summary");
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

// What a cloud file says beyond its points.
struct CloudFileFacts {
  // Where its sensors stood (a PCD's VIEWPOINT, a PTX file's scanners); with more than one, each
  // point's attribute "scan" says whose it is.
  std::vector<lsqsurf::core::Vec3d> sensors;
  std::array<double, 3> shift = {0, 0, 0};  // Taken off its coordinates (a georeferenced LAS file's).
};

// A cloud file's upload: .drc as it is (one part), other formats read and encoded with unit
// normals in parts of client::kPointsPerPart points. An empty path uploads nothing. `facts`,
// when given, receives what the file says beyond its points.
absl::StatusOr<client::PartSource> CloudUpload(const std::string& path,
                                               int64_t points_per_part = client::kPointsPerPart,
                                               CloudFileFacts* facts = nullptr);
// The same in one part, for jobs that take their cloud whole (track); "" for an empty path.
absl::StatusOr<std::string> CloudBytes(const std::string& path);

// Follows a job to its end; returns the exit code and the final job through `out`.
int Watch(const Globals& g, const std::string& id, v1::Job* out);

// Whether an output path names a directory (ends with '/' or is one).
bool IsDirectoryOutput(const std::string& path);

// Downloads the artifact `name` of job `id` to `path` through WriteResult; the mesh ("") of a job
// that delivered it in parts is joined as it comes (client::WriteMeshParts), or written tile by
// tile as .drc files when `path` is a directory (client::WriteMeshPartFiles). `partial`: of a job
// still running, the mesh parts done so far (they are a part of the final mesh). `job`: the job's
// record when the caller has it. Returns the exit code.
int FetchToFile(const Globals& g, const std::string& id, const std::string& name, const std::string& path,
                const v1::Job* job = nullptr, bool partial = false);

// Writes a fetched artifact to `path`: Draco meshes convert to the extension's format;
// pictures, tables and text are written as they are.
int WriteResult(const std::string& bytes, const std::string& name, const std::string& path);

// The statistics of a finished job: all of them (`all`), or a summary line (triangles, closed,
// components, time) and the repairs made to the input.
void PrintStatistics(const v1::Job& job, bool all);
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
    if (encoded->missing_vertices > 0) {
      std::fprintf(stderr, "%s: %lld vertices without a value were filled in from their neighbours\n", path.c_str(),
                   static_cast<long long>(encoded->missing_vertices));
    }
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
  std::string csg_expression;                    // Method csg: the solid (no upload).
  int64_t part_points = client::kPointsPerPart;  // Points per upload part (SubmitJobRequest.input_part_end).
  struct EditFlags {
    std::string source, ball, set, refit;
    bool remove = false;
  } edit;  // Method edit.

  // Fills EditParams from `lsqsurf edit ID --ball x,y,z,r --set degree=N | --refit error_threshold=E | --remove`.
  absl::Status ApplyEdit(v1::JobSpec* spec) const;
  absl::Status UseFileFacts(const CloudFileFacts& facts, bool quiet, v1::JobSpec* spec) const;

  int Run(const Globals& g, bool wait) const;
  void AddPartFlag(CLI::App* command) {
    command
        ->add_option("--part-points", part_points,
                     "points per upload part: a cloud is read and sent a part at a time (a PU job over tile_points "
                     "then also delivers its mesh in parts, joined as they come)")
        ->capture_default_str()
        ->check(CLI::Range(int64_t{1000}, int64_t{1} << 30));
  }
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

// track: the parameters' flags are generated from TrackParams; every one left out keeps the
// server's default. The interface, the field and the grid take names or files, and h, by hand.
struct TrackCommand {
  std::string interface, field, output;
  std::optional<double> h;
  bool pictures = false;
  double turntable = 0;
  GeneratedFlags params{"track", *v1::TrackParams::descriptor()};
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
