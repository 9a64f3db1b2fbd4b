// lsqsurf-bench — accuracy, time and memory of the engines on the shared benchmark meshes.
//
// For every model × size × noise case it samples a cloud from the ground-truth mesh (area-uniform,
// normals interpolated from the vertex normals or, with --face-normals, the faces' own; optional
// Gaussian noise along the normal as a fraction of the bounding-box diagonal), reconstructs it,
// and compares the result with the ground truth (see worker/core/surface_distance.h). Each case
// runs in a child process so that its peak RSS is its own. With --server, the same clouds also go
// through a real lsqsurfd started on a free loopback port, driven by the real client (upload,
// reconstruct, download). With --poisson-depth (built with -DLSQSURF_BENCH_POISSON=ON), screened
// Poisson reconstructs the same cloud in the same run, and a ratio line compares the two.
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "client/client.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/sampling.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/core/surface_distance.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/surface_job.h"
#include "worker/pu/pu_tiles.h"
#if LSQSURF_WITH_POISSON
#include "bench/poisson_open3d.h"
#endif

namespace {

using namespace lsqsurf;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

struct CaseResult {
  double seconds = 0;
  double peak_mib = 0;
  int64_t triangles = 0;
  double chamfer = 0, hausdorff = 0, normal_consistency = 0, far_fraction = 0;
  double hausdorff_with_vertices = 0;  // Corners included (core::CompareResult).
  double min_angle_p1 = 0;             // Degrees: 1 % of the triangles have a smaller smallest angle.
  bool watertight = false;
  int64_t components = 0, boundary_edges = 0;
  int64_t vertices = 0;  // Welded by position.
  // Against another result of the same case (--tile-points): Chamfer and Hausdorff, shares of the diagonal.
  double chamfer_to_other = 0, hausdorff_to_other = 0;
  std::string error;
};

std::string Serialize(const CaseResult& r) {
  return core::StrCat(r.seconds, " ", r.triangles, " ", r.chamfer, " ", r.hausdorff, " ", r.normal_consistency, " ",
                      r.far_fraction, " ", r.watertight ? 1 : 0, " ", r.components, " ", r.boundary_edges, " ",
                      r.min_angle_p1, " ", r.peak_mib, " ", r.hausdorff_with_vertices, " ", r.vertices, " ",
                      r.chamfer_to_other, " ", r.hausdorff_to_other, "\n", r.error);
}

CaseResult Deserialize(const std::string& s) {
  CaseResult r;
  std::istringstream in(s);
  int wt = 0;
  in >> r.seconds >> r.triangles >> r.chamfer >> r.hausdorff >> r.normal_consistency >> r.far_fraction >> wt >>
      r.components >> r.boundary_edges >> r.min_angle_p1 >> r.peak_mib >> r.hausdorff_with_vertices >> r.vertices >>
      r.chamfer_to_other >> r.hausdorff_to_other;
  r.watertight = wt != 0;
  std::getline(in, r.error);
  std::getline(in, r.error);
  return r;
}

// The peak resident memory of this process so far, MiB.
double PeakMibSoFar() {
  struct rusage usage {};
  ::getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;
}

// Runs `body` in a child process; its result comes back through a pipe, its peak RSS from wait4
// unless the body measured its own (before the comparison with the ground truth, which holds
// both meshes and their search trees: the reconstruction's peak is what is reported).
// The parent must never run parallel work itself: a child forked after oneTBB started its
// worker threads runs everything on one thread (measured: 2× slower on 2 cores).
CaseResult InChild(const std::function<CaseResult()>& body) {
  int fds[2];
  if (::pipe(fds) != 0) return {.error = "pipe failed"};
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::close(fds[0]);
    const std::string out = Serialize(body());
    (void)!::write(fds[1], out.data(), out.size());
    ::_exit(0);
  }
  ::close(fds[1]);
  std::string text;
  char buf[4096];
  ssize_t n;
  while ((n = ::read(fds[0], buf, sizeof(buf))) > 0) text.append(buf, static_cast<size_t>(n));
  ::close(fds[0]);
  int status = 0;
  struct rusage usage {};
  ::wait4(pid, &status, 0, &usage);
  CaseResult r = text.empty() ? CaseResult{.error = "the case crashed"} : Deserialize(text);
  if (!(r.peak_mib > 0)) r.peak_mib = static_cast<double>(usage.ru_maxrss) / 1024.0;
  return r;
}

void Measure(const core::TriangleMesh& truth, const core::TriangleMesh& mesh, size_t samples, CaseResult& r) {
  // Welded by position, as STL export and most tools see the mesh.
  const core::TriangleMesh welded = core::WeldByPosition(mesh);
  const core::MeshTopology t = core::AnalyzeTopology(welded);
  r.vertices = static_cast<int64_t>(welded.vertices.size());
  r.triangles = t.faces;
  r.watertight = t.watertight();
  r.components = t.components;
  r.boundary_edges = t.boundary_edges;
  r.min_angle_p1 = core::MeasureTriangleQuality(mesh).min_angle_p1;
  core::LocalJobContext ctx;
  core::CompareParams p;
  p.samples = samples;
  auto cmp = core::CompareMeshes(truth, mesh, p, ctx);
  if (!cmp.ok()) {
    r.error = std::string(cmp.status().message());
    return;
  }
  r.chamfer = cmp->chamfer;
  r.hausdorff = cmp->hausdorff;
  r.hausdorff_with_vertices = cmp->hausdorff_with_vertices;
  r.normal_consistency = cmp->normal_consistency;
  r.far_fraction = cmp->far_fraction;
}

int RunTool(const std::string& cmd) { return std::system((cmd + " > /dev/null 2>&1").c_str()); }

// RunTool, also giving the largest resident set of the command and of what it waited for.
int RunToolMeasured(const std::string& cmd, double* peak_mib) {
  const std::string line = cmd + " > /dev/null 2>&1";
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::execl("/bin/sh", "sh", "-c", line.c_str(), static_cast<char*>(nullptr));
    ::_exit(127);
  }
  int status = 0;
  rusage usage{};
  if (pid < 0 || ::wait4(pid, &status, 0, &usage) != pid) return -1;
  *peak_mib = static_cast<double>(usage.ru_maxrss) / 1024.0;
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

// Runs a command and returns its first output line (empty on failure).
std::string FirstLine(const std::string& cmd) {
  FILE* p = ::popen((cmd + " 2>/dev/null").c_str(), "r");
  if (p == nullptr) return "";
  char buf[256] = {0};
  const bool got = std::fgets(buf, sizeof(buf), p) != nullptr;
  const int status = ::pclose(p);
  std::string line = got && status == 0 ? buf : "";
  while (!line.empty() && (line.back() == '\n' || line.back() == '\r')) line.pop_back();
  return line;
}

struct BenchOptions {
  std::string data_dir = "../shared/data/meshes";
  std::vector<std::string> models = {"stanford-bunny", "spot", "fandisk"};
  std::vector<size_t> sizes = {100000};
  std::vector<double> noises = {0.0};
  std::vector<std::string> methods = {"iamls"};
  std::vector<std::string> params;  // name=value, as the CLI's --param; each goes to the methods that have it.
  size_t samples = 1'000'000;
  bool server = false;
  bool drop_normals = false;
  bool face_normals = false;
  bool show_statistics = false;
  bool streamed = false;
  std::string save_dir;
  std::string bin_dir;
  int poisson_depth = 0;
  int64_t tile_points = 0;  // PU: also run every case in tiles of this many points and compare.
};

// One benchmark case: a model's ground truth and a cloud sampled from it.
struct BenchCase {
  const core::TriangleMesh& truth;
  const core::PointCloud& cloud;
  std::string model;
  size_t points = 0;
  double noise = 0;
  std::string method;
};

void Print(const BenchCase& c, const char* mode, const CaseResult& r) {
  if (!r.error.empty()) {
    std::printf("%-15s %8zu %6.4f %-6s %-7s failed: %s\n", c.model.c_str(), c.points, c.noise, c.method.c_str(), mode,
                r.error.c_str());
  } else {
    std::printf("%-15s %8zu %6.4f %-6s %-7s %8.2f %9.0f %10lld %10.3e %10.3e %7.4f %6s %6lld %10.3e %9.1f %10.3e\n",
                c.model.c_str(), c.points, c.noise, c.method.c_str(), mode, r.seconds, r.peak_mib,
                static_cast<long long>(r.triangles), r.chamfer, r.hausdorff, r.normal_consistency,
                r.watertight ? "yes" : "no", static_cast<long long>(r.components), r.far_fraction, r.min_angle_p1,
                r.hausdorff_with_vertices);
  }
  std::fflush(stdout);
}

void SaveResult(const BenchOptions& o, const BenchCase& c, const core::TriangleMesh& mesh) {
  if (o.save_dir.empty()) return;
  const auto path = fs::path(o.save_dir) / core::StrCat(c.model, "-", c.points, "-", c.noise, "-", c.method, ".ply");
  if (absl::Status s = io::WriteMeshFile(path.string(), mesh); !s.ok()) {
    std::fprintf(stderr, "%s\n", s.ToString().c_str());
  }
}

// The engine called in this process's child, as the service's worker calls it; its mesh also
// goes to `keep` where given (what --tile-points compares against).
CaseResult RunDirect(const BenchOptions& o, const core::ParamSet& params, const BenchCase& c,
                     const std::string& keep = "") {
  return InChild([&] {
    CaseResult r;
    core::LocalJobContext ctx;
    const auto start = Clock::now();
    auto result = jobs::ReconstructSurface(c.method, params, c.cloud, ctx);
    r.seconds = Since(start);
    r.peak_mib = PeakMibSoFar();
    if (!result.ok()) {
      r.error = std::string(result.status().message());
      return r;
    }
    SaveResult(o, c, result->mesh);
    if (!keep.empty()) (void)io::WriteMeshFile(keep, result->mesh);
    if (o.show_statistics) {
      for (const auto& [name, value] : result->statistics) std::printf("  %s=%g\n", name.c_str(), value);
      std::fflush(stdout);
    }
    Measure(c.truth, result->mesh, o.samples, r);
    return r;
  });
}

// A method's parameters and the name=value texts it took: each text goes to the methods whose
// table has its name. Errors: kInvalidArgument (a bad text, value or combination).
struct MethodParams {
  core::ParamSet params;
  std::vector<std::string> texts;
};
absl::StatusOr<MethodParams> ParseParams(const std::string& method, const std::vector<std::string>& texts) {
  auto params = jobs::DefaultParams(method);
  if (!params.ok()) return params.status();
  MethodParams out{*std::move(params), {}};
  const std::vector<core::ParamInfo> known = out.params.Describe();
  for (const auto& p : texts) {
    const size_t eq = p.find('=');
    if (eq == std::string::npos) return absl::InvalidArgumentError(core::StrCat("bad --param ", p, "; use NAME=VALUE"));
    const std::string name = p.substr(0, eq);
    if (std::none_of(known.begin(), known.end(), [&](const core::ParamInfo& i) { return i.name == name; })) continue;
    LSQSURF_RETURN_IF_ERROR(out.params.Parse(name, p.substr(eq + 1)));
    out.texts.push_back(p);
  }
  LSQSURF_RETURN_IF_ERROR(out.params.Validate());
  return out;
}

// The case again in tiles of o.tile_points points, measured against the truth and against the
// untiled mesh in `untiled` (both ways): a surface must not depend on how the work was cut.
void RunTiledComparison(const BenchOptions& o, const std::vector<std::string>& texts, const BenchCase& c,
                        const CaseResult& direct, const std::string& untiled) {
  std::vector<std::string> tiled_texts = texts;
  tiled_texts.push_back(core::StrCat("tile_points=", o.tile_points));
  auto params = ParseParams(c.method, tiled_texts);
  if (!params.ok()) return (void)std::printf("    tiled: %s\n", params.status().ToString().c_str());
  const CaseResult tiled = InChild([&] {
    CaseResult r = RunDirect(o, params->params, c, untiled + ".tiled.ply");
    if (!r.error.empty()) return r;
    auto tiled_mesh = io::ReadMeshFile(untiled + ".tiled.ply");
    auto whole = io::ReadMeshFile(untiled);
    if (!tiled_mesh.ok() || !whole.ok()) return CaseResult{.error = "the meshes to compare could not be read"};
    core::LocalJobContext ctx;
    core::CompareParams p;
    p.samples = o.samples;
    auto cmp = core::CompareMeshes(*whole, *tiled_mesh, p, ctx);
    if (!cmp.ok()) return CaseResult{.error = std::string(cmp.status().message())};
    r.chamfer_to_other = cmp->chamfer;
    r.hausdorff_to_other = cmp->hausdorff;
    return r;
  });
  Print(c, "tiled", tiled);
  if (tiled.error.empty() && direct.error.empty()) {
    std::printf(
        "    tiled (%lld points a tile) / untiled: vertices %.4fx, closed %s / %s, components %lld / %lld; "
        "apart: Chamfer %.2e, Hausdorff %.2e of the diagonal\n",
        static_cast<long long>(o.tile_points),
        static_cast<double>(tiled.vertices) / static_cast<double>(direct.vertices), tiled.watertight ? "yes" : "no",
        direct.watertight ? "yes" : "no", static_cast<long long>(tiled.components),
        static_cast<long long>(direct.components), tiled.chamfer_to_other, tiled.hausdorff_to_other);
  }
}

// A cloud sampled from a mesh chunk by chunk (each chunk its own seed), never whole in memory;
// normals interpolated from the vertex normals, or the faces' own (--face-normals).
class SampledSource final : public pu::PointSource {
 public:
  SampledSource(const core::TriangleMesh& mesh, size_t points, double noise_sigma, bool face_normals)
      : mesh_(mesh), points_(points), noise_sigma_(noise_sigma), face_normals_(face_normals) {}
  absl::Status ForEachChunk(const std::function<absl::Status(const core::PointCloud&)>& visit) const override {
    constexpr size_t kChunk = 1 << 20;
    for (size_t begin = 0, chunk = 0; begin < points_; begin += kChunk, ++chunk) {
      LSQSURF_RETURN_IF_ERROR(visit(
          core::SampleCloud(mesh_, std::min(kChunk, points_ - begin), 1234 + chunk, noise_sigma_, !face_normals_)));
    }
    return absl::OkStatus();
  }

 private:
  const core::TriangleMesh& mesh_;
  size_t points_;
  double noise_sigma_;
  bool face_normals_;
};

// The tiled PU engine on a cloud streamed from the sampler (pu_tiles.h): the cloud never sits in
// memory, so the peak is the engine's own plus the mesh it returns.
CaseResult RunStreamed(const BenchOptions& o, const core::ParamSet& params, const BenchCase& c) {
  return InChild([&] {
    CaseResult r;
    const auto* p = params.As<jobs::PuJobParams>();
    if (p == nullptr) return CaseResult{.error = "--streamed runs the pu method only"};
    core::LocalJobContext ctx;
    const double diagonal = core::Diagonal(core::BoundingBox(c.truth.vertices));
    const SampledSource source(c.truth, c.points, c.noise * diagonal, o.face_normals);
    pu::MeshSink sink;
    const auto start = Clock::now();
    auto tiled = pu::ReconstructTiled(source, p->fit, p->extract, p->tiles, sink, ctx);
    r.seconds = Since(start);
    r.peak_mib = PeakMibSoFar();
    if (!tiled.ok()) return CaseResult{.error = std::string(tiled.status().message())};
    std::printf(
        "  streamed: %.2f s per million points, %lld tiles at level %d (largest %lld points), measuring %.1f s "
        "(reading and bucketing %.1f s, spacing and noise %.1f s), fitting %.1f s, extracting %.1f s, %.0f MiB "
        "of tile files, %lld seam vertices\n",
        r.seconds * 1e6 / static_cast<double>(c.points), static_cast<long long>(tiled->tiles), tiled->tile_level,
        static_cast<long long>(tiled->largest_tile), tiled->measure_seconds, tiled->scan_seconds,
        tiled->spacing_seconds, tiled->fit.fit_seconds,
        tiled->extract.tree_seconds + tiled->extract.tracking_seconds + tiled->extract.marching_seconds +
            tiled->extract.crease_seconds + tiled->extract.relax_seconds,
        static_cast<double>(tiled->scratch_bytes) / (1 << 20), static_cast<long long>(tiled->seam_vertices));
    std::fflush(stdout);
    SaveResult(o, c, sink.mesh());
    Measure(c.truth, sink.mesh(), o.samples, r);
    return r;
  });
}

#if LSQSURF_WITH_POISSON
void RunPoisson(const BenchOptions& o, const BenchCase& c, const CaseResult& direct) {
  const CaseResult poisson = InChild([&] {
    CaseResult r;
    const auto start = Clock::now();
    auto mesh = bench::ScreenedPoisson(c.cloud, {.depth = o.poisson_depth});
    r.seconds = Since(start);
    r.peak_mib = PeakMibSoFar();
    if (!mesh.ok()) {
      r.error = std::string(mesh.status().message());
      return r;
    }
    Measure(c.truth, *mesh, o.samples, r);
    return r;
  });
  Print(c, "poisson", poisson);
  if (direct.error.empty() && poisson.error.empty()) {
    std::printf("    %s / poisson depth %d: time %.2fx, peak memory %.2fx, Chamfer %.2fx, triangles %.2fx\n",
                c.method.c_str(), o.poisson_depth, direct.seconds / poisson.seconds, direct.peak_mib / poisson.peak_mib,
                direct.chamfer / poisson.chamfer,
                static_cast<double>(direct.triangles) / static_cast<double>(poisson.triangles));
  }
}
#endif

// A real lsqsurfd on a free loopback port, in its own data folder; stopped on destruction.
class BenchServer {
 public:
  BenchServer(const std::string& bin_dir, const fs::path& work, const std::string& flags = "") : work_(work) {
    const std::string data = (work / "server-data").string();
    fs::remove_all(data);
    const std::string addr_file = (work / "address").string();
    fs::remove(addr_file);
    const std::string start =
        core::StrCat("(", bin_dir, "/lsqsurfd --listen 127.0.0.1:0 --data-dir ", data, " ", flags,
                     " 2>/dev/null & echo $! > ", work.string(), "/pid; wait) | head -1 > ", addr_file, " &");
    (void)std::system(start.c_str());
    // The server prints "listening on ADDRESS" once it serves; the shell writes it on exit of head.
    for (int i = 0; i < 100 && address_.empty(); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      std::ifstream in(addr_file);
      std::string word;
      in >> word >> word >> address_;
    }
    std::ifstream pid_in(work / "pid");
    pid_in >> pid_;
  }
  ~BenchServer() {
    if (pid_ > 0) ::kill(static_cast<pid_t>(pid_), SIGTERM);
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
  }
  const std::string& address() const { return address_; }
  double PeakMib() const {
    std::ifstream status(core::StrCat("/proc/", pid_, "/status"));
    for (std::string line; std::getline(status, line);) {
      if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
    }
    return 0;
  }

 private:
  fs::path work_;
  std::string address_;
  long pid_ = 0;
};

void PrintNewestJobStatistics(const std::string& address) {
  auto listed = client::Client(address).List(1);
  if (!listed.ok() || listed->jobs_size() == 0) return;
  for (const auto& st : listed->jobs(0).statistics()) std::printf("  service %s=%g\n", st.name().c_str(), st.value());
}

// The accuracy of the mesh a client run (exit code `rc`) wrote to `path`, measured in a child:
// this process must never start oneTBB's workers (see InChild).
CaseResult MeasureMeshFile(const BenchOptions& o, const BenchCase& c, const std::string& path, int rc) {
  if (rc != 0) {
    CaseResult failed;
    failed.error = core::StrCat("the client failed (exit ", rc, ")");
    return failed;
  }
  return InChild([&] {
    CaseResult m;
    auto mesh = io::ReadMeshFile(path);
    if (!mesh.ok())
      m.error = std::string(mesh.status().message());
    else
      Measure(c.truth, *mesh, o.samples, m);
    return m;
  });
}

// The same cloud through a real server and the real client: upload, reconstruct, download.
void RunService(const BenchOptions& o, const BenchCase& c, const std::vector<std::string>& params,
                const fs::path& work) {
  const std::string cloud_path = (work / "cloud.drc").string(), mesh_path = (work / "mesh.drc").string();
  const auto t_encode = Clock::now();
  auto encoded = io::EncodeDracoPointCloud(c.cloud, {});
  const double encode_s = Since(t_encode);
  const auto t_decode = Clock::now();
  (void)io::DecodeDracoPointCloud(*encoded);
  const double decode_s = Since(t_decode);
  (void)io::WriteFileAtomically(cloud_path, *encoded);
  BenchServer server(o.bin_dir, work);
  const std::string client = core::StrCat(o.bin_dir, "/lsqsurf -q --server ", server.address(), " ");
  std::string param_args;
  for (const auto& p : params) param_args += " --param " + p;
  const auto t_upload = Clock::now();
  const std::string submitted = FirstLine(client + "submit " + cloud_path + " --method " + c.method + param_args);
  const double upload_s = Since(t_upload);
  // That job only measured the upload: cancel it so it does not delay the timed one.
  if (!submitted.empty()) RunTool(client + "cancel " + submitted);
  // While the timed job uploads and runs, another caller reads a job's state: its latency shows
  // whether the service's threads wait on uploads, engines or the disk.
  std::atomic<bool> polling{true};
  std::vector<double> latencies_ms;
  std::thread poller([&] {
    client::Client api(server.address());
    while (polling) {
      const auto t = Clock::now();
      (void)api.Get(submitted);
      latencies_ms.push_back(1e3 * Since(t));
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  });
  const auto t_e2e = Clock::now();
  const int rc =
      RunTool(client + "reconstruct " + cloud_path + " -o " + mesh_path + " --method " + c.method + param_args);
  const double seconds = Since(t_e2e);
  polling = false;
  poller.join();
  if (o.show_statistics) PrintNewestJobStatistics(server.address());  // The timed job.
  const double peak = server.PeakMib();
  CaseResult r = MeasureMeshFile(o, c, mesh_path, submitted.empty() ? -1 : rc);
  r.seconds = seconds;
  r.peak_mib = peak;
  Print(c, "service", r);
  std::printf("    draco: %.2f MB, encode %.0f ms, decode %.0f ms; upload+validate %.2f s (%.1f MB/s)\n",
              static_cast<double>(encoded->size()) / 1e6, encode_s * 1e3, decode_s * 1e3, upload_s,
              static_cast<double>(encoded->size()) / 1e6 / upload_s);
  if (!latencies_ms.empty()) {
    std::sort(latencies_ms.begin(), latencies_ms.end());
    auto at = [&](double q) {
      return latencies_ms[static_cast<size_t>(q * static_cast<double>(latencies_ms.size() - 1))];
    };
    std::printf("    GetJob during upload and run: %zu calls, median %.2f ms, p99 %.2f ms, max %.2f ms\n",
                latencies_ms.size(), at(0.5), at(0.99), latencies_ms.back());
  }
}

// The sampled cloud as a binary PLY with normals, written chunk by chunk as a scanner would.
absl::Status WriteSampledPly(const SampledSource& source, size_t points, const std::string& path) {
  static_assert(std::endian::native == std::endian::little, "the PLY body is written in native order");
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << "ply\nformat binary_little_endian 1.0\nelement vertex " << points
      << "\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n"
         "property float nz\nend_header\n";
  std::vector<float> rows;
  LSQSURF_RETURN_IF_ERROR(source.ForEachChunk([&](const core::PointCloud& chunk) {
    rows.clear();
    for (size_t i = 0; i < chunk.size(); ++i) {
      rows.insert(rows.end(), chunk.positions[i].data(), chunk.positions[i].data() + 3);
      rows.insert(rows.end(), chunk.normals[i].data(), chunk.normals[i].data() + 3);
    }
    out.write(reinterpret_cast<const char*>(rows.data()), static_cast<std::streamsize>(rows.size() * sizeof(float)));
    return out ? absl::OkStatus() : absl::DataLossError(core::StrCat(path, ": write failed (disk full?)"));
  }));
  out.close();
  return out ? absl::OkStatus() : absl::DataLossError(core::StrCat(path, ": write failed (disk full?)"));
}

// A sampled cloud written to a PLY file, sent by the real client in parts to a real server,
// and the mesh fetched: time, the peaks of both processes, and the mesh's accuracy.
void RunStreamedService(const BenchOptions& o, const BenchCase& c, const std::vector<std::string>& params,
                        const fs::path& work) {
  const std::string cloud_path = (work / "cloud.ply").string(), mesh_path = (work / "mesh.ply").string();
  const double diagonal = core::Diagonal(core::BoundingBox(c.truth.vertices));
  const auto t_write = Clock::now();
  if (absl::Status s =
          WriteSampledPly(SampledSource(c.truth, c.points, c.noise * diagonal, o.face_normals), c.points, cloud_path);
      !s.ok()) {
    std::printf("  %s\n", std::string(s.message()).c_str());
    return;
  }
  const double write_s = Since(t_write);
  BenchServer server(o.bin_dir, work, "--max-points 2000000000 --max-upload-mib 65536");
  std::string param_args;
  for (const auto& p : params) param_args += " --param " + p;
  double client_peak = 0;
  const auto start = Clock::now();
  const int rc = RunToolMeasured(core::StrCat(o.bin_dir, "/lsqsurf -q --server ", server.address(), " reconstruct ",
                                              cloud_path, " -o ", mesh_path, " --method ", c.method, param_args),
                                 &client_peak);
  const double seconds = Since(start);
  const double server_peak = server.PeakMib();
  fs::remove(cloud_path);
  if (o.show_statistics) PrintNewestJobStatistics(server.address());
  CaseResult r = MeasureMeshFile(o, c, mesh_path, rc);
  r.seconds = seconds;
  r.peak_mib = server_peak;
  Print(c, "served", r);
  std::printf(
      "    through the service: %.2f s per million points; peak memory: server %.0f MiB, client %.0f MiB "
      "(the PLY file, %.0f MiB, written in %.1f s)\n",
      seconds * 1e6 / static_cast<double>(c.points), server_peak, client_peak,
      static_cast<double>(c.points) * 24.0 / (1 << 20), write_s);
  std::fflush(stdout);
  fs::remove(mesh_path);
}

// With several methods: Chamfer and wall time of each method on each case, one row per method
// (the seed's Figure 11 comparison as numbers).
struct SummaryCell {
  std::string column;  // model/points/noise
  std::string method;
  CaseResult result;
};
void PrintSummary(const std::vector<std::string>& methods, const std::vector<SummaryCell>& cells) {
  std::vector<std::string> columns;
  for (const auto& c : cells) {
    if (std::find(columns.begin(), columns.end(), c.column) == columns.end()) columns.push_back(c.column);
  }
  std::printf("\nChamfer (share of the diagonal) / wall seconds, direct:\n%-7s", "method");
  for (const auto& col : columns) std::printf(" %24s", col.c_str());
  for (const auto& m : methods) {
    std::printf("\n%-7s", m.c_str());
    for (const auto& col : columns) {
      std::string text = "-";
      for (const auto& c : cells) {
        if (c.method != m || c.column != col) continue;
        char buf[64];
        std::snprintf(buf, sizeof(buf), "%.2e / %.2f", c.result.chamfer, c.result.seconds);
        text = c.result.error.empty() ? buf : "failed";
      }
      std::printf(" %24s", text.c_str());
    }
  }
  std::printf("\n");
}

}  // namespace

int main(int argc, char** argv) {
  BenchOptions o;
  CLI::App app{"lsqsurf-bench: engines vs ground-truth meshes"};
  app.add_option("--data", o.data_dir, "folder with <model>.obj ground-truth meshes")->capture_default_str();
  app.add_option("--models", o.models, "model names")->capture_default_str();
  app.add_option("--sizes", o.sizes, "cloud sizes")->capture_default_str();
  app.add_option("--noise", o.noises, "noise sigma as a fraction of the diagonal (0 = clean)")->capture_default_str();
  app.add_option("--method,--methods", o.methods, "surface methods, comma-separated or repeated")
      ->delimiter(',')
      ->capture_default_str();
  app.add_option("--param", o.params, "method parameter name=value (repeatable)");
  app.add_option("--samples", o.samples, "samples per surface for the distances")->capture_default_str();
  app.add_flag("--server", o.server, "also run every case through lsqsurfd and the lsqsurf client");
  app.add_option("--save", o.save_dir,
                 "write every direct (or --streamed) result to DIR/<model>-<points>-<noise>-<method>.ply");
  app.add_flag("--stats", o.show_statistics, "print the engine's statistics of every direct run");
  app.add_flag("--streamed", o.streamed,
               "pu only: sample each cloud chunk by chunk into the tiled engine (never whole in memory) instead of "
               "the direct and server runs; with --server, write it chunk by chunk to a PLY file that the client "
               "sends in parts to lsqsurfd (the peaks of both are printed)");
  app.add_flag("--no-normals", o.drop_normals, "drop the sampled normals (the engines estimate them)");
  app.add_flag("--face-normals", o.face_normals,
               "sample the faces' own normals, as a CAD exporter gives them (default: interpolated vertex normals)");
  app.add_option("--bin", o.bin_dir, "folder with lsqsurfd and lsqsurf (default: beside this program)");
  app.add_option("--tile-points", o.tile_points,
                 "pu: also run every case in tiles of this many points (tile_points) and compare the two surfaces");
  app.add_option("--poisson-depth", o.poisson_depth,
                 "also run screened Poisson (Open3D) at this depth on every cloud; 0 = off");
  CLI11_PARSE(app, argc, argv);
#if !LSQSURF_WITH_POISSON
  if (o.poisson_depth > 0) {
    std::fprintf(stderr, "--poisson-depth needs a build with -DLSQSURF_BENCH_POISSON=ON (and libopen3d-dev)\n");
    return 2;
  }
#endif
  if (o.bin_dir.empty()) o.bin_dir = fs::canonical("/proc/self/exe").parent_path().string();
  std::vector<MethodParams> params;
  for (const auto& m : o.methods) {
    auto p = ParseParams(m, o.params);
    if (!p.ok()) {
      std::fprintf(stderr, "%s: %s\n", m.c_str(), p.status().ToString().c_str());
      return 2;
    }
    params.push_back(*std::move(p));
  }
  for (const auto& p : o.params) {
    if (std::none_of(params.begin(), params.end(), [&](const MethodParams& m) {
          return std::find(m.texts.begin(), m.texts.end(), p) != m.texts.end();
        })) {
      std::fprintf(stderr, "--param %s: no method given has that parameter (see lsqsurf methods)\n", p.c_str());
      return 2;
    }
  }
  std::vector<SummaryCell> summary;

  const fs::path work = fs::temp_directory_path() / ("lsqsurf-bench-" + std::to_string(::getpid()));
  fs::create_directories(work);
  std::printf("%-15s %8s %6s %-6s %-7s %8s %9s %10s %10s %10s %7s %6s %6s %10s %9s %10s\n", "model", "points", "noise",
              "method", "mode", "wall_s", "peak_MiB", "triangles", "chamfer", "hausdorff", "normals", "closed", "comps",
              "far>1e-3", "angle_p1", "hd_corners");
  for (const auto& model : o.models) {
    auto truth = io::ReadMeshFile((fs::path(o.data_dir) / (model + ".obj")).string());
    if (!truth.ok()) {
      std::fprintf(stderr, "%s\n", truth.status().ToString().c_str());
      return 1;
    }
    const double diag = core::Diagonal(core::BoundingBox(truth->vertices));
    for (size_t n : o.sizes) {
      for (double noise : o.noises) {
        core::PointCloud cloud =
            o.streamed ? core::PointCloud{} : core::SampleCloud(*truth, n, 1234, noise * diag, !o.face_normals);
        if (o.drop_normals) cloud.normals.clear();
        for (size_t m = 0; m < o.methods.size(); ++m) {
          const BenchCase c{*truth, cloud, model, n, noise, o.methods[m]};
          if (o.streamed) {
            if (o.server) {
              RunStreamedService(o, c, params[m].texts, work);
            } else {
              Print(c, "stream", RunStreamed(o, params[m].params, c));
            }
            continue;
          }
          const bool compare_tiles = o.tile_points > 0 && o.methods[m] == "pu";
          const std::string untiled = (work / "untiled.ply").string();
          const CaseResult direct = RunDirect(o, params[m].params, c, compare_tiles ? untiled : "");
          Print(c, "direct", direct);
          if (compare_tiles) RunTiledComparison(o, params[m].texts, c, direct, untiled);
          summary.push_back({core::StrCat(model, "/", n, "/", noise), o.methods[m], direct});
#if LSQSURF_WITH_POISSON
          if (o.poisson_depth > 0 && m + 1 == o.methods.size()) RunPoisson(o, c, direct);
#endif
          if (o.server) RunService(o, c, params[m].texts, work);
        }
      }
    }
  }
  if (o.methods.size() > 1) PrintSummary(o.methods, summary);
  // The last server may still be writing its database as it stops: its files may vanish
  // under the sweep, so errors are ignored.
  std::error_code ignored;
  fs::remove_all(work, ignored);
  return 0;
}
