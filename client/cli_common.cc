#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <limits>
#include <optional>
#include <set>

#include "client/cli.h"
#include "worker/core/address.h"
#include "worker/core/status.h"
#include "worker/core/volume_mesh.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

int Fail(const std::string& message, int code) {
  std::fprintf(stderr, "lsqsurf: %s\n", message.c_str());
  return code;
}

int FailStatus(const char* what, const absl::Status& s) {
  const int code =
      s.code() == absl::StatusCode::kUnavailable || s.code() == absl::StatusCode::kAborted ? kExitLocal : kExitFailed;
  return Fail(StrCat(what, ": ", s.message(), " (", static_cast<int>(s.code()), ")"), code);
}

void ConnectionFlags::AddTo(CLI::App& app) {
  app.add_option("--tls-ca", ca, "PEM certificates to trust for the server's ($LSQSURF_TLS_CA; default: the system's)");
  app.add_option("--tls-cert", cert, "PEM client certificate, for mutual TLS ($LSQSURF_TLS_CERT)");
  app.add_option("--tls-key", key, "PEM private key of --tls-cert ($LSQSURF_TLS_KEY)");
  app.add_option("--tls-server-name", server_name,
                 "name the server's certificate must carry, when not the address's host ($LSQSURF_TLS_SERVER_NAME)");
  app.add_flag("--tls", tls, "use TLS with the system's roots (implied by --tls-*, and for non-loopback servers)");
  app.add_flag("--plaintext", plaintext, "talk to a non-loopback server without TLS");
  app.add_option("--token-file", token_file,
                 "file holding the token for a server with tokens (default: $LSQSURF_TOKEN)");
}

absl::StatusOr<client::ConnectOptions> ConnectionFlags::Resolve(const std::string& server) {
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

client::Client Connect(const Globals& g) { return client::Client(g.server, g.connect); }

namespace {

// `points_per_part` points at most in a part; a .drc file is one part as it is.
absl::StatusOr<client::PartSource> CloudFileParts(const std::string& path, int64_t points_per_part,
                                                  CloudFileFacts* facts) {
  if (path.empty()) return client::PartSource([] { return absl::StatusOr<std::string>(std::string()); });
  if (lsqsurf::io::FormatFromPath(path).value_or(lsqsurf::io::FileFormat::kPly) == lsqsurf::io::FileFormat::kDraco) {
    auto bytes = lsqsurf::io::ReadFileBytes(path);
    if (!bytes.ok()) return bytes.status();
    auto held = std::make_shared<std::string>(*std::move(bytes));
    return client::PartSource([held]() -> absl::StatusOr<std::string> { return std::exchange(*held, {}); });
  }
  // Read as it is sent: the client holds one part of a cloud larger than its memory.
  auto points = lsqsurf::io::OpenPointStream(path);
  if (!points.ok()) return points.status();
  if (facts != nullptr) *facts = {(*points)->sensor_positions(), (*points)->coordinate_shift()};
  auto parts = client::StreamParts(*std::move(points), {}, points_per_part);
  // Errors name the file (the readers' do already).
  return client::PartSource([parts, path]() -> absl::StatusOr<std::string> {
    auto part = parts();
    if (part.ok() || std::string(part.status().message()).starts_with(path)) return part;
    return absl::Status(part.status().code(), StrCat(path, ": ", part.status().message()));
  });
}

}  // namespace

absl::StatusOr<std::string> CloudBytes(const std::string& path) {
  auto parts = CloudFileParts(path, std::numeric_limits<int64_t>::max(), nullptr);
  if (!parts.ok()) return parts.status();
  return (*parts)();
}

absl::StatusOr<client::PartSource> CloudUpload(const std::string& path, int64_t points_per_part,
                                               CloudFileFacts* facts) {
  return CloudFileParts(path, points_per_part, facts);
}

namespace {

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

}  // namespace

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

bool IsDirectoryOutput(const std::string& path) {
  std::error_code ignored;
  return path.ends_with('/') || std::filesystem::is_directory(path, ignored);
}

int FetchToFile(const Globals& g, const std::string& id, const std::string& name, const std::string& path,
                const v1::Job* job, bool partial) {
  client::Client c = Connect(g);
  std::vector<std::string> parts;
  if (name.empty()) {  // The mesh: one artifact, or parts to join as they come.
    absl::StatusOr<v1::Job> got = job != nullptr ? absl::StatusOr<v1::Job>(*job) : c.Get(id);
    if (!got.ok()) return FailStatus("fetch", got.status());
    parts = client::MeshParts(*got);
    if (got->state() == v1::JOB_STATE_RUNNING && !partial) {
      return Fail(StrCat("job ", id, " is still running; wait for it, or fetch --partial for the surface done so far"));
    }
    if (partial && parts.empty() && got->state() == v1::JOB_STATE_RUNNING) {
      return Fail(StrCat("job ", id, " has no mesh parts yet (only a PU job streamed from parts delivers them)"));
    }
  }
  const auto fetch_part = [&](size_t i) { return c.Fetch(id, parts[i]); };
  if (IsDirectoryOutput(path)) {
    if (parts.empty()) {
      return Fail(StrCat("-o ", path,
                         " names a directory, which takes a mesh delivered in parts (one .drc per "
                         "tile); job ",
                         id, " has none: name a file"));
    }
    auto written = client::WriteMeshPartFiles(parts.size(), fetch_part, path);
    if (!written.ok()) return FailStatus("fetch", written.status());
    std::fprintf(stderr, "wrote %zu tiles to %s\n", written->size(), path.c_str());
    return 0;
  }
  if (!parts.empty()) {
    const absl::Status s = client::WriteMeshParts(parts.size(), fetch_part, path);
    return s.ok() ? 0 : FailStatus("fetch", s);
  }
  auto bytes = c.Fetch(id, name);
  if (!bytes.ok()) return FailStatus("fetch", bytes.status());
  return WriteResult(*bytes, name, path);
}

namespace {

// Says what the server made of the sensor: positions set aside (they hid too many points), one
// inferred, depth steps undone.
void PrintSensorNotes(const v1::Job& job) {
  std::optional<double> hidden_share, toward_viewpoint, depth_step, moved, inferred;
  for (const auto& s : job.statistics()) {
    if (s.name() == "viewpoint_hidden_share") hidden_share = s.value();
    if (s.name() == "normals_toward_viewpoint") toward_viewpoint = s.value();
    if (s.name() == "depth_step") depth_step = s.value();
    if (s.name() == "depth_steps_moved") moved = s.value();
    if (s.name() == "viewpoint_inferred") inferred = s.value();
  }
  if (depth_step && moved) {
    std::fprintf(stderr,
                 "  the points lay on the depth steps of a stereo or depth camera (%g apart at the median depth): "
                 "%.0f%% were moved along their rays onto the surface between the steps (undo_depth_steps=false "
                 "keeps them)%s\n",
                 *depth_step, 100 * *moved,
                 inferred == 1.0 ? "; no sensor position was given, and the steps place it at the origin" : "");
  }
  if (hidden_share && toward_viewpoint == 0.0) {
    std::fprintf(stderr,
                 "  the sensor positions given hide %.0f%% of the points behind others, so they are not where "
                 "these points were seen from: normals were oriented by propagation instead\n",
                 100 * *hidden_share);
  }
}

}  // namespace

void PrintStatistics(const v1::Job& job, bool all) {
  if (all) {
    for (const auto& s : job.statistics()) std::fprintf(stderr, "  %s = %g\n", s.name().c_str(), s.value());
    PrintSensorNotes(job);
    return;
  }
  // One line of what a user checks first, then what the server had to repair in the input.
  std::optional<double> triangles, boundary_edges, components;
  std::string repaired;
  const auto& repairs = lsqsurf::core::kVolumeRepairStatistics;
  for (const auto& s : job.statistics()) {
    if (s.name() == "triangles") triangles = s.value();
    if (s.name() == "boundary_edges") boundary_edges = s.value();
    if (s.name() == "components") components = s.value();
    if (std::find(repairs.begin(), repairs.end(), s.name()) != repairs.end() && s.value() > 0) {
      repaired += StrCat(repaired.empty() ? "" : ", ", static_cast<int64_t>(s.value()), " ", s.name());
    }
  }
  std::string line;
  if (triangles) line = StrCat(static_cast<int64_t>(*triangles), " triangles");
  if (boundary_edges) {
    line += *boundary_edges == 0 ? ", closed"
                                 : StrCat(", open (", static_cast<int64_t>(*boundary_edges), " boundary edges)");
  }
  if (components)
    line += StrCat(", ", static_cast<int64_t>(*components), *components == 1 ? " component" : " components");
  if (job.updated_ms() > job.created_ms()) {
    char seconds[32];
    std::snprintf(seconds, sizeof seconds, "%.1f", static_cast<double>(job.updated_ms() - job.created_ms()) / 1e3);
    line += StrCat(line.empty() ? "" : "; ", "in ", seconds, " s");
  }
  if (!line.empty()) std::fprintf(stderr, "  %s\n", line.c_str());
  if (!repaired.empty()) std::fprintf(stderr, "  input repaired: %s\n", repaired.c_str());
  PrintSensorNotes(job);
  std::fprintf(stderr, "  %d statistics: --stats, or lsqsurf status %s\n", job.statistics_size(), job.id().c_str());
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
    } else if (view.has_samples() && response->samples() < view.samples()) {
      std::fprintf(stderr, "; %d samples per pixel, the most this GL offers", response->samples());
    }
    std::fprintf(stderr, ")\n");
  }
  return 0;
}

}  // namespace lsqsurf::cli

namespace lsqsurf::cli {
namespace {

// The fields of RenderOptions that draw a volume field: `render --volume` names them.
const std::set<std::string> kVolumeViewFields = {"volume_mode", "opacity", "iso_value", "volume_resolution",
                                                 "ray_step"};

}  // namespace

void ViewFlags::AddTo(CLI::App* cmd) {
  cmd->add_option("--size", size, "picture width and height in pixels (--width and --height set one)");
  fields.AddTo(cmd, {.aliases = {{"up_axis", "--up"},
                                 {"azimuth_deg", "--azimuth"},
                                 {"elevation_deg", "--elevation"},
                                 {"fov_deg", "--fov"},
                                 {"flat_shading", "--flat"}},
                     .skip = kVolumeViewFields});
}

absl::StatusOr<v1::RenderOptions> ViewFlags::Options() const {
  v1::RenderOptions view;
  if (size) view.set_width(*size), view.set_height(*size);
  LSQSURF_RETURN_IF_ERROR(fields.Apply(&view));
  return view;
}

void VolumeViewFlags::AddTo(CLI::App* cmd) {
  cmd->add_flag("--volume", volume, "draw a volume job's field by direct volume rendering");
  cmd->add_option("--iso-ray", iso_ray, "draw the isosurface of this value by ray casting instead");
  cmd->add_option("--opacity", opacity, StrCat(TableHelp("view", "opacity"), " (e.g. 0:0,0.5:0.2,1:0.8)"));
  cmd->add_option("--transfer", transfer, "file with the opacity points, one 't alpha' or 't:alpha' per line");
  fields.AddTo(cmd, {.aliases = {{"volume_resolution", "--resolution"}, {"ray_step", "--step"}},
                     .only = {"volume_resolution", "ray_step"}});
}

absl::Status VolumeViewFlags::Apply(v1::RenderOptions* view) const {
  std::string points = opacity;
  if (!transfer.empty()) {
    LSQSURF_ASSIGN_OR_RETURN(const std::string text, lsqsurf::io::ReadFileBytes(transfer));
    points.clear();
    std::string line;
    for (char c : text + "\n") {
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
  return fields.Apply(view);
}

}  // namespace lsqsurf::cli
