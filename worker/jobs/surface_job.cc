#include "worker/jobs/surface_job.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <optional>

#include "worker/core/mesh_metrics.h"
#include "worker/core/outliers.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/extract/j1a_isosurface.h"
#include "worker/io/draco_codec.h"
#include "worker/io/mesh_part.h"
#include "worker/jobs/pictures.h"
#include "worker/jobs/shared_extraction.h"
#include "worker/jobs/surface_input.h"
#include "worker/jobs/surface_points.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {
namespace {

constexpr char kMeshArtifact[] = "mesh.drc";

template <class P>
void AddExtractionHints(core::ParamTable<P>& t) {
  t.template Real<&P::cell_size>("cell_size", 0.1, 16, "h",
                                 "spacing of the extraction vertices (J1a leaves are twice as large, with vertices at "
                                 "their centres and face and edge midpoints)")
      .template Integer<&P::refine_steps>("refine_steps", 0, 20, "steps", "root-refinement steps per crossing edge")
      .template Integer<&P::wall_levels>("wall_levels", -1, extract::kMaxProbeLevels, "levels",
                                         "times at most that a J1a leaf is split where its tetrahedra miss a wall or "
                                         "gap thinner than they are (found where points face against each other); "
                                         "0 = off, -1 = chosen (2; iaMLS: 0 where it does not fade thin walls, as on "
                                         "noisy clouds that are not mostly walls)");
}

const core::ParamTable<IamlsJobParams>& IamlsTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<IamlsJobParams>();
    t->Include(&IamlsJobParams::fit, mls::IamlsParamTable());
    AddExtractionHints(*t);
    t->Choice<&IamlsJobParams::extractor>(
        "extractor",
        {{"j1a", static_cast<int>(SurfaceExtractor::kJ1a), "J1a tetrahedra on an adaptive octree"},
         {"grid", static_cast<int>(SurfaceExtractor::kUniformGrid),
          "surface-following uniform Kuhn grid (a little faster)"}},
        "where the zero set is extracted");
    t->Include(&IamlsJobParams::points, PointParamsTable());
    t->Real<&IamlsJobParams::min_component>("min_component", 0, 100, "kernel widths",
                                            "components whose bounding-box diagonal is below this many kernel "
                                            "widths (h/epsilon) are removed as unresolved; 0 keeps all");
    return t;
  }();
  return *table;
}

// The table of an MLS method on the shared extractor: its engine's table, the extraction hints
// and the points' parameters.
template <class P>
const core::ParamTable<P>& MlsTable(const core::ParamTable<decltype(P::fit)>& fit_table) {
  static const auto* table = [&] {
    auto* t = new core::ParamTable<P>();
    t->Include(&P::fit, fit_table);
    AddExtractionHints(*t);
    t->Include(&P::points, PointParamsTable());
    return t;
  }();
  return *table;
}

const core::ParamTable<PuJobParams>& PuTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuJobParams>();
    t->Include(&PuJobParams::fit, pu::PuParamTable())
        .Include(&PuJobParams::extract, pu::PuExtractParamTable())
        .Include(&PuJobParams::tiles, pu::PuTileParamTable())
        .Include(&PuJobParams::points, PointParamsTable())
        .Flag<&PuJobParams::keep_function>("keep_function",
                                           "keep the fitted function with the results (function.lqpu) so that csg "
                                           "and edit jobs can use it without refitting; about 40 bytes per point");
    return t;
  }();
  return *table;
}

void AddStatistic(Statistics* stats, std::string name, double value) {
  for (auto& [n, v] : *stats) {
    if (n == name) {
      v = value;
      return;
    }
  }
  stats->emplace_back(std::move(name), value);
}

using StatFn = std::function<void(std::string, double)>;
using KeepFn = std::function<void(std::string, std::string)>;  // An artifact to store beside the mesh.

// What a method's run reports to and is bounded by besides its parameters.
struct MethodRun {
  StatFn stat;
  KeepFn keep;
  int64_t memory_bytes = 0;  // The job's memory limit (RunEnvironment::memory_bytes).
  // The cloud read part by part, for methods that stream it (SurfaceMethod::streams); the cloud handed over
  // beside it is then empty.
  const pu::PointSource* source = nullptr;
  // Where given, a streamed cloud's mesh is delivered in parts (kMeshPartArtifact) as they are made, never
  // whole; their count goes to *parts_written and the mesh returned is empty.
  ArtifactWriteFn write;
  int64_t* parts_written = nullptr;
  TiledRun tiled;  // Where a tiled run's point files go and its tiles run.
};

// Each tile's part of the surface an artifact as soon as it is made (io/mesh_part.h).
class PartArtifactSink final : public pu::SurfaceSink {
 public:
  explicit PartArtifactSink(const ArtifactWriteFn& write) : write_(write) {}
  absl::Status AddTile(const pu::TileOutput& tile) override {
    const std::string bytes =
        io::EncodeMeshPart(tile.first_vertex, tile.vertices, tile.normals, tile.attributes, tile.faces);
    LSQSURF_RETURN_IF_ERROR(write_(MeshPartArtifact(parts_), bytes));
    for (const auto& f : tile.faces) topology_.AddFace(f[0], f[1], f[2]);
    ++parts_;
    vertices_ += static_cast<int64_t>(tile.vertices.size());
    faces_ += static_cast<int64_t>(tile.faces.size());
    return absl::OkStatus();
  }
  int64_t parts() const { return parts_; }
  int64_t vertices() const { return vertices_; }
  int64_t faces() const { return faces_; }
  // Of the parts joined by vertex number (the welded seams included).
  core::MeshTopology Topology() { return topology_.Result(); }

 private:
  const ArtifactWriteFn& write_;
  int64_t parts_ = 0, vertices_ = 0, faces_ = 0;
  core::TopologyAccumulator topology_;
};

absl::StatusOr<extract::IsosurfaceResult> RunIamls(const IamlsJobParams& p, const core::PointCloud& cloud,
                                                   core::JobContext& ctx, const MethodRun& run) {
  const StatFn& stat = run.stat;
  const auto start = std::chrono::steady_clock::now();
  core::SubContext build_ctx(ctx, "building iaMLS", 0.0, 0.3);
  auto field = mls::BuildIamls(cloud, p.fit, build_ctx);
  if (!field.ok()) return field.status();
  const mls::IamlsStats& fit = (*field)->stats();
  stat("fit_seconds", core::SecondsSince(start));
  stat("spacing", (*field)->spacing());
  // The parameters used, given or chosen from the noise (noise_level as in pu, a share of the
  // diagonal; reported only when something was chosen).
  stat("epsilon_used", fit.epsilon);
  stat("iterations_used", fit.iterations);
  stat("cutoff_used", fit.cutoff);
  stat("normal_sigma_used", fit.normal_sigma);
  stat("thin_walls_used", fit.thin_walls ? 1 : 0);
  if (fit.noise_level >= 0) {
    stat("noise_level", fit.noise_level);
    stat("noise_to_spacing", fit.noise_ratio);
  }
  if (fit.largest_eigenvalue > 0) stat("largest_eigenvalue", fit.largest_eigenvalue);
  if (fit.epsilon_lowered > 0) stat("epsilon_lowered", fit.epsilon_lowered);
  if (fit.iterations_cut) stat("iterations_cut", 1);
  stat("thin_samples", static_cast<double>(fit.thin_samples));
  if (!fit.residuals.empty()) stat("final_residual_over_h", fit.residuals.back());
  const auto extract_start = std::chrono::steady_clock::now();
  core::SubContext extract_ctx(ctx, "extracting surface", 0.3, 1.0);
  // Wall probes where the field fades thin walls: on clean clouds, and on noisy ones that are mostly
  // walls, whose probes then take the noise's wider spread.
  const int wall_levels = p.wall_levels >= 0 ? p.wall_levels : (fit.thin_walls ? kChosenWallLevels : 0);
  stat("wall_levels_used", wall_levels);
  auto extracted = ExtractShared(**field, cloud,
                                 {.vertex_spacing = p.cell_size * (*field)->spacing(),
                                  .refine_steps = p.refine_steps,
                                  .wall_levels = wall_levels,
                                  .noisy_walls = !mls::ChooseIamlsParameters(fit.noise_ratio).thin_walls,
                                  .extractor = p.extractor,
                                  .memory_bytes = run.memory_bytes},
                                 extract_ctx);
  if (!extracted.ok()) return extracted;
  stat("extract_seconds", core::SecondsSince(extract_start));
  if (p.min_component > 0) {
    const double kernel_width = (*field)->spacing() / fit.epsilon;
    stat("removed_components",
         static_cast<double>(core::RemoveSmallComponents(extracted->mesh, p.min_component * kernel_width)));
  }
  return extracted;
}

// The MLS surfaces without an extractor of their own: build the function with `build`, then
// extract it on J1a leaves sized by its spacing.
template <class P, class Build>
absl::StatusOr<extract::IsosurfaceResult> RunOnSharedExtractor(const P& p, const core::PointCloud& cloud,
                                                               core::JobContext& ctx, const MethodRun& run,
                                                               Build build) {
  const StatFn& stat = run.stat;
  core::SubContext build_ctx(ctx, "indexing points", 0.0, 0.05);
  auto field = build(cloud, p.fit, build_ctx);
  if (!field.ok()) return field.status();
  stat("spacing", (*field)->spacing());
  const auto start = std::chrono::steady_clock::now();
  core::SubContext extract_ctx(ctx, "extracting surface", 0.05, 1.0);
  auto extracted = ExtractShared(**field, cloud,
                                 {.vertex_spacing = p.cell_size * (*field)->spacing(),
                                  .refine_steps = p.refine_steps,
                                  .wall_levels = p.wall_levels >= 0 ? p.wall_levels : kChosenWallLevels,
                                  .extractor = SurfaceExtractor::kJ1a,
                                  .memory_bytes = run.memory_bytes},
                                 extract_ctx);
  if (extracted.ok()) stat("extract_seconds", core::SecondsSince(start));
  return extracted;
}

template <mls::AlgebraicFit kFit>
absl::StatusOr<extract::IsosurfaceResult> RunAlgebraic(const AlgebraicJobParams<kFit>& p, const core::PointCloud& cloud,
                                                       core::JobContext& ctx, const MethodRun& run) {
  return RunOnSharedExtractor(p, cloud, ctx, run, &mls::BuildAlgebraicMls);
}

template <mls::GaussianFit kFit>
absl::StatusOr<extract::IsosurfaceResult> RunGaussian(const GaussianJobParams<kFit>& p, const core::PointCloud& cloud,
                                                      core::JobContext& ctx, const MethodRun& run) {
  return RunOnSharedExtractor(p, cloud, ctx, run, &mls::BuildGaussianMls);
}

void PuStatistics(const pu::PuStats& s, const StatFn& stat) {
  stat("fit_seconds", s.fit_seconds);
  stat("spacing_seconds", s.spacing_seconds);
  stat("index_seconds", s.index_seconds);
  stat("mean_spacing", s.mean_spacing);
  stat("noise_level", s.noise_estimate);
  stat("error_threshold_used", s.error_threshold);
  stat("min_points_used", s.min_points);
  for (size_t d = 0; d < s.fits_per_degree.size(); ++d) {
    stat(core::StrCat("fits_degree_", d), static_cast<double>(s.fits_per_degree[d]));
  }
  stat("fits_quadric", static_cast<double>(s.quadric_fits));
  stat("fits_sharp_edge", static_cast<double>(s.sharp_edges));
  stat("fits_sharp_corner", static_cast<double>(s.sharp_corners));
  stat("fits_above_threshold", static_cast<double>(s.unmet_threshold));
  for (size_t d = 0; d < s.leaves_per_depth.size(); ++d) {
    if (s.leaves_per_depth[d] > 0) stat(core::StrCat("leaves_depth_", d), static_cast<double>(s.leaves_per_depth[d]));
  }
}

void ExtractionStatistics(const extract::IsosurfaceStats& s, const StatFn& stat) {
  stat("tetrahedra", static_cast<double>(s.tetrahedra));
  stat("crease_vertices", static_cast<double>(s.crease_vertices));
  stat("crease_corners", static_cast<double>(s.crease_corners));
  stat("snapped_corners", static_cast<double>(s.snapped_corners));
  stat("relaxed_vertices", static_cast<double>(s.relaxed_vertices));
  stat("flipped_edges", static_cast<double>(s.flipped_edges));
}

// The job's extraction within its memory, closing small holes once the surface is whole.
pu::PuExtractParams PuExtraction(const PuJobParams& p, const MethodRun& run) {
  pu::PuExtractParams extract = p.extract;
  extract.max_leaves = LeavesWithin(run.memory_bytes, extract.max_leaves);
  extract.max_hole_edges = kClosedHoleEdges;
  return extract;
}

// A cloud of more than tile_points points, tile by tile (pu_tiles.h). No function is kept: there
// is none whole, and csg and edit jobs need one.
absl::StatusOr<extract::IsosurfaceResult> RunTiledPu(const PuJobParams& p, const pu::PointSource& source,
                                                     core::JobContext& ctx, const MethodRun& run) {
  const StatFn& stat = run.stat;
  const pu::PuExtractParams extract = PuExtraction(p, run);
  pu::MeshSink mesh;
  std::optional<PartArtifactSink> parts;
  if (run.source != nullptr && run.write) parts.emplace(run.write);
  pu::SurfaceSink& sink = parts.has_value() ? static_cast<pu::SurfaceSink&>(*parts) : mesh;
  auto tiled = run.tiled.exchange != nullptr
                   ? ReconstructTiledShared(source, p.fit, extract, p.tiles, sink, ctx, run.tiled)
                   : pu::ReconstructTiled(source, p.fit, extract, p.tiles, sink, ctx, run.tiled.scratch_dir);
  if (!tiled.ok()) return tiled.status();
  if (run.tiled.exchange != nullptr) {
    stat("replicas", run.tiled.exchange->Servers());
    stat("reused_tiles", static_cast<double>(run.tiled.exchange->Reused()));
  }
  if (parts.has_value()) {
    stat("mesh_parts", static_cast<double>(parts->parts()));
    stat("triangles", static_cast<double>(parts->faces()));
    stat("vertices", static_cast<double>(parts->vertices()));
    // The mesh is never whole here: its closure is counted as the parts go (an edge with a third
    // face shows as a boundary edge).
    const core::MeshTopology topology = parts->Topology();
    stat("boundary_edges", static_cast<double>(topology.boundary_edges));
    stat("misoriented_edges", static_cast<double>(topology.misoriented_edges));
    stat("degenerate_faces", static_cast<double>(topology.degenerate_faces));
    stat("components", static_cast<double>(topology.components));
    if (run.parts_written != nullptr) *run.parts_written = parts->parts();
  }
  PuStatistics(tiled->fit, stat);
  stat("measure_seconds", tiled->measure_seconds);
  stat("tiles", static_cast<double>(tiled->tiles));
  stat("tile_level", tiled->tile_level);
  stat("largest_tile_points", static_cast<double>(tiled->largest_tile));
  stat("tile_margin", tiled->margin);
  stat("tile_scratch_bytes", static_cast<double>(tiled->scratch_bytes));
  stat("seam_vertices", static_cast<double>(tiled->seam_vertices));
  stat("max_support", tiled->frame.max_support);
  ExtractionStatistics(tiled->extract, stat);
  extract::IsosurfaceResult result;
  result.stats = tiled->extract;
  result.mesh = std::move(mesh.mesh());
  return result;
}

absl::StatusOr<extract::IsosurfaceResult> RunPu(const PuJobParams& p, const core::PointCloud& cloud,
                                                core::JobContext& ctx, const MethodRun& run) {
  if (run.source != nullptr) return RunTiledPu(p, *run.source, ctx, run);
  if (static_cast<int64_t>(cloud.size()) > p.tiles.tile_points) return RunTiledPu(p, pu::CloudSource(cloud), ctx, run);
  const StatFn& stat = run.stat;
  const KeepFn& keep = run.keep;
  pu::PuExtractParams extract = PuExtraction(p, run);
  // In the frame a tiled build fixes, as its one tile, so that the surface does not depend on
  // tile_points; no other tile's sums must match this one's, so they run in the kd-tree's order.
  core::SubContext build_ctx(ctx, "fitting", 0.0, 0.4);
  const auto frame_start = std::chrono::steady_clock::now();
  const auto frame = pu::MeasureFrame(cloud, p.fit, extract, p.tiles, build_ctx);
  if (!frame.ok()) return frame.status();
  stat("frame_seconds", core::SecondsSince(frame_start));
  auto field = pu::BuildPuInFrame(cloud, *frame, nullptr, build_ctx, pu::SumOrder::kAsFound);
  if (!field.ok()) return field.status();
  // Measured on merged scans with fill_holes: the short rim left spot's four views in 3 pieces
  // (1 with the full reach) and fandisk's lidar 4× farther from the truth.
  if (p.points.fill_holes) (*field)->KeepFullReachPastRims();
  PuStatistics((*field)->stats(), stat);
  const auto start = std::chrono::steady_clock::now();
  core::SubContext extract_ctx(ctx, "extracting surface", 0.4, 1.0);
  extract.marching.trace = p.keep_function;  // Local edits re-extract only what they change.
  auto extracted = pu::Extract(**field, extract, extract_ctx);
  if (!extracted.ok()) return extracted;
  stat("extract_seconds", core::SecondsSince(start));
  if (p.keep_function) {
    const auto keep_start = std::chrono::steady_clock::now();
    std::string bytes = pu::SerializePu(**field);
    stat("function_bytes", static_cast<double>(bytes.size()));
    keep(kPuFunctionArtifact, std::move(bytes));
    bytes = pu::SerializeSurface(extracted->mesh, extracted->trace, extract);
    stat("surface_bytes", static_cast<double>(bytes.size()));
    keep(kPuSurfaceArtifact, std::move(bytes));
    stat("keep_seconds", core::SecondsSince(keep_start));
  }
  // After keeping: the edits join onto the surface as marched (Extract left its holes open).
  if (extract.marching.trace) extract::CloseSmallHoles(*extracted, extract.max_hole_edges);
  ExtractionStatistics(extracted->stats, stat);
  return extracted;
}

// The peak memory of a surface job, from the cloud's size and the extraction cell: about `per_point` bytes a
// point for the function and `per_vertex` a vertex of the mesh (measured on the spot model at 50k to 800k
// points: iaMLS 425 and 400, PU 130 and 500). The vertices come from the cell: the shared extractor puts 4.4 a
// point on a surface sampled at h = 2 spacings with cells of h, scaling with the square of the cell; PU's
// adaptive cells are up to 8 times as large where the surface is flat, so its count is taken at that coarsest
// size (a low estimate: what is refused certainly would not fit).
struct CloudSize {
  int64_t points = 0;
  double diagonal = 0;         // Of the bounding box.
  int64_t streamed_bytes = 0;  // The Draco parts a streamed cloud is read from (0: decoded whole).
};

struct MemoryModel {
  double per_point = 0, per_vertex = 0;
};

// An explicit spacing h, in units of the cloud's spacing as estimated from its size alone (the bounding box
// diagonal squared over the points, about a surface's area per point), taken 4 times more coarsely than that.
double SpacingsOf(double h, const CloudSize& size) {
  if (size.points <= 0 || size.diagonal <= 0) return 1;
  return 2.0 * h / (0.5 * size.diagonal / std::sqrt(static_cast<double>(size.points)));
}

MemoryEstimate EstimateMemory(const MemoryModel& model, double vertices_per_point, const CloudSize& size,
                              std::string hint) {
  const double points = static_cast<double>(size.points);
  const double bytes = points * (model.per_point + model.per_vertex * vertices_per_point);
  return {static_cast<int64_t>(std::min(bytes, 9e18)), std::move(hint)};
}

template <class P>
MemoryEstimate EstimateSharedExtraction(const P& p, const CloudSize& size) {
  // h in spacings: spacing_scale, or an explicit spacing over the estimated one.
  const double h = p.fit.spacing > 0 ? SpacingsOf(p.fit.spacing, size) : p.fit.spacing_scale;
  const double cell = p.cell_size * h / 2;  // In units of the h = 2 spacings measured.
  return EstimateMemory({425, 400}, 4.4 / (cell * cell), size, "raise cell_size or the spacing, or split the cloud");
}

MemoryEstimate EstimatePu(const PuJobParams& p, const CloudSize& size) {
  const double coarsest = p.extract.cell_size * 8 / 5;  // Relative to the default cell of 5 spacings.
  const double vertices_per_point = 2.0 / (coarsest * coarsest);
  if (size.points <= p.tiles.tile_points) {
    return EstimateMemory({130, 500}, vertices_per_point, size, "raise cell_size, or split the cloud");
  }
  // Tiled: the decoded cloud (24 bytes a point) or the parts it streams from, one tile at a time with its margin
  // (at most about 1.75 times its points on the bench's scans), and the welded mesh (about 60 bytes a vertex
  // with its faces, normal and labels).
  const double points = static_cast<double>(size.points);
  const double cloud = size.streamed_bytes > 0 ? static_cast<double>(size.streamed_bytes) : 24 * points;
  const double tile = 1.75 * static_cast<double>(p.tiles.tile_points);
  const double bytes = cloud + tile * (130 + 500 * vertices_per_point) + 60 * vertices_per_point * points;
  return {static_cast<int64_t>(std::min(bytes, 9e18)), "lower tile_points or raise cell_size"};
}

// One entry per method: its description, how its typed parameters run, and its memory.
struct SurfaceMethod {
  MethodInfo info;
  std::function<absl::StatusOr<extract::IsosurfaceResult>(const core::ParamSet&, const core::PointCloud&,
                                                          core::JobContext&, const MethodRun&)>
      run;
  std::function<const PointParams*(const core::ParamSet&)> points;
  std::function<MemoryEstimate(const core::ParamSet&, const CloudSize&)> memory;
  // Whether a cloud of this many points in parts is read part by part (MethodRun::source) rather
  // than decoded whole; null: never.
  std::function<bool(const core::ParamSet&, int64_t points)> streams;
};

template <class P, class Run, class Memory>
SurfaceMethod MakeMethod(std::string name, std::string description, const core::ParamTable<P>& table, Run run,
                         Memory memory, std::vector<std::string> attributes = {}) {
  SurfaceMethod m;
  m.info = {std::move(name), std::move(description), core::ParamSet(table), std::move(attributes), {kInputUpload}};
  m.info.input_in_parts = true;  // Parts after the first are concatenated, or streamed (Streaming).
  m.run = [run](const core::ParamSet& params, const core::PointCloud& cloud, core::JobContext& ctx,
                const MethodRun& how) -> absl::StatusOr<extract::IsosurfaceResult> {
    const P* p = params.As<P>();
    if (p == nullptr) return absl::InternalError("parameters of another method");
    return run(*p, cloud, ctx, how);
  };
  m.points = [](const core::ParamSet& params) -> const PointParams* {
    const P* p = params.As<P>();
    return p ? &p->points : nullptr;
  };
  m.memory = [memory](const core::ParamSet& params, const CloudSize& size) {
    const P* p = params.As<P>();
    return p ? memory(*p, size) : MemoryEstimate{};
  };
  return m;
}

template <class P>
SurfaceMethod Streaming(SurfaceMethod m, bool (*streams)(const P&, int64_t)) {
  m.streams = [streams](const core::ParamSet& params, int64_t points) {
    const P* p = params.As<P>();
    return p != nullptr && streams(*p, points);
  };
  return m;
}

const std::vector<SurfaceMethod>& SurfaceMethods() {
  static const auto* methods = new std::vector<SurfaceMethod>{
      MakeMethod("iamls", "iterated approximate MLS surface (seed §4), extracted on a tetrahedral grid", IamlsTable(),
                 RunIamls, EstimateSharedExtraction<IamlsJobParams>),
      Streaming<PuJobParams>(
          MakeMethod("pu",
                     "twofold adaptive partition-of-unity implicit (seed §2): orthogonal-polynomial fits of "
                     "adaptive degree on an adaptive octree, extracted on its J1a tetrahedra",
                     PuTable(), RunPu, EstimatePu, {"depth", "degree", "feature"}),
          [](const PuJobParams& p, int64_t points) { return points > p.tiles.tile_points; }),
      MakeMethod("ramls",
                 "robust algebraic MLS surface (seed §3): closed-form normal-driven sphere fits, extracted on J1a "
                 "tetrahedra",
                 MlsTable<RamlsJobParams>(mls::AlgebraicMlsParamTable(mls::AlgebraicFit::kRamls)),
                 RunAlgebraic<mls::AlgebraicFit::kRamls>, EstimateSharedExtraction<RamlsJobParams>),
      MakeMethod("apss",
                 "algebraic point set surface (Guennebaud & Gross): normal-constrained sphere fits weighted by beta, "
                 "extracted on J1a tetrahedra",
                 MlsTable<ApssJobParams>(mls::AlgebraicMlsParamTable(mls::AlgebraicFit::kApss)),
                 RunAlgebraic<mls::AlgebraicFit::kApss>, EstimateSharedExtraction<ApssJobParams>),
      MakeMethod("aamls",
                 "Adamson-Alexa MLS surface: distance to the plane through the Gaussian-weighted centroid along the "
                 "weighted mean normal, extracted on J1a tetrahedra",
                 MlsTable<AamlsJobParams>(mls::GaussianMlsParamTable()), RunGaussian<mls::GaussianFit::kAdamsonAlexa>,
                 EstimateSharedExtraction<AamlsJobParams>),
      MakeMethod("imls",
                 "Kolluri's implicit MLS surface: Gaussian-weighted mean of the points' tangent-plane distances, "
                 "extracted on J1a tetrahedra",
                 MlsTable<ImlsJobParams>(mls::GaussianMlsParamTable()), RunGaussian<mls::GaussianFit::kKolluri>,
                 EstimateSharedExtraction<ImlsJobParams>),
  };
  return *methods;
}

const SurfaceMethod* FindSurfaceMethod(const std::string& name) {
  for (const auto& m : SurfaceMethods()) {
    if (m.info.name == name) return &m;
  }
  return nullptr;
}

class SurfaceKind final : public TypedJobKind<core::ParamSet, SurfaceInput> {
 public:
  std::string_view name() const override { return "surface"; }

  std::vector<MethodInfo> Methods() const override {
    std::vector<MethodInfo> out;
    for (const auto& m : SurfaceMethods()) out.push_back(m.info);
    return out;
  }

  absl::StatusOr<Checked> Decode(const JobSpec& spec, const core::ParamSet& params, const Uploads& uploads,
                                 const InputLimits& limits) const override {
    const SurfaceMethod* m = FindSurfaceMethod(spec.method);
    if (m == nullptr || m->points(params) == nullptr) return absl::InternalError("not a surface method");
    const auto streams = [&](int64_t points) { return m->streams && m->streams(params, points); };
    auto input = DecodeSurfaceInput(uploads, *m->points(params), limits, streams);
    if (!input.ok()) return input.status();
    CloudSize size{input->points, input->diagonal, 0};
    for (const core::ByteView& part : input->parts) size.streamed_bytes += static_cast<int64_t>(part.size());
    MemoryEstimate memory = m->memory(params, size);
    return Checked{size.points, *std::move(input), std::move(memory)};
  }

  absl::StatusOr<Statistics> RunDecoded(const JobSpec& spec, const core::ParamSet& params, SurfaceInput input,
                                        RunEnvironment& env) const override {
    const ArtifactWriteFn write = [&env](const std::string& name, std::string_view bytes) {
      return env.sink.Write(name, bytes);
    };
    const TiledRun tiled{env.scratch_dir, env.tiles};
    auto result = input.parts.empty() ? ReconstructSurface(spec.method, params, std::move(input.cloud), env.context,
                                                           env.memory_bytes, tiled)
                                      : ReconstructStreamed(spec.method, params, DracoPartsSource(input.parts),
                                                            input.points, env.context, env.memory_bytes, write, tiled);
    if (!result.ok()) return result.status();
    if (result->mesh_parts == 0) {
      LSQSURF_RETURN_IF_ERROR(DeliverMesh(result->mesh, spec, env, &result->statistics));
    } else if (spec.preview.enabled) {
      env.context.ReportProgress("drawing the preview", 0.99);
      PreviewFailures failures;
      if (const absl::Status p = DrawPreviewOfParts(result->mesh_parts, spec.preview, env); !p.ok()) {
        failures.Add(kPreviewArtifact, p);
      }
      LSQSURF_RETURN_IF_ERROR(failures.Report(env, result->statistics));
    }
    for (const auto& [name, bytes] : result->kept) LSQSURF_RETURN_IF_ERROR(env.sink.Write(name, bytes));
    return std::move(result->statistics);
  }
};

}  // namespace

absl::StatusOr<std::string> ReadKeptArtifact(RunEnvironment& env, const std::string& job_id, std::string_view name) {
  auto stored = env.read_result ? env.read_result(job_id, std::string(name))
                                : absl::StatusOr<std::string>(absl::UnavailableError("no job store"));
  if (stored.ok()) return stored;
  const absl::StatusCode code = stored.status().code();
  if (code != absl::StatusCode::kNotFound && code != absl::StatusCode::kFailedPrecondition) return stored.status();
  return absl::FailedPreconditionError(stored.status().message());
}

absl::StatusOr<std::unique_ptr<pu::PuFunction>> ReadKeptPuFunction(RunEnvironment& env, const std::string& job_id) {
  auto stored = ReadKeptArtifact(env, job_id, kPuFunctionArtifact);
  if (stored.status().code() == absl::StatusCode::kFailedPrecondition) {
    return absl::FailedPreconditionError(core::StrCat("no kept PU function (", stored.status().message(),
                                                      "); use a succeeded pu or edit job run with keep_function=true"));
  }
  if (!stored.ok()) return stored.status();
  return pu::DeserializePu(*stored);
}

absl::Status DeliverMesh(const core::TriangleMesh& mesh, const JobSpec& spec, RunEnvironment& env,
                         Statistics* statistics) {
  LSQSURF_RETURN_IF_ERROR(env.context.CheckCancelled());  // Coding millions of faces takes seconds.
  auto encoded = EncodeResultMesh(mesh, spec.mesh_position_bits, statistics, &env.context);
  if (!encoded.ok()) return encoded.status();
  LSQSURF_RETURN_IF_ERROR(env.sink.Write(kMeshArtifact, *encoded));
  if (spec.preview.enabled) {
    env.context.ReportProgress("drawing the preview", 0.99);
    PreviewFailures failures;
    if (const absl::Status p = DrawPreview(mesh, spec.preview, env); !p.ok()) failures.Add(kPreviewArtifact, p);
    LSQSURF_RETURN_IF_ERROR(failures.Report(env, *statistics));
  }
  return absl::OkStatus();
}

const JobKind& SurfaceJobKind() {
  static const SurfaceKind kind;
  return kind;
}

namespace {

absl::StatusOr<const SurfaceMethod*> CheckedMethod(const std::string& method, const core::ParamSet& params) {
  const SurfaceMethod* m = FindSurfaceMethod(method);
  if (m == nullptr || m->points(params) == nullptr) {
    return absl::InvalidArgumentError(core::StrCat("'", method, "' is not a surface method with these parameters"));
  }
  LSQSURF_RETURN_IF_ERROR(params.Validate());
  return m;
}

// The method run on a cloud with normals (or on `source`, its mesh through `write` where given),
// the mesh and its statistics into `result`.
absl::Status RunMethod(const SurfaceMethod& m, const core::ParamSet& params, const core::PointCloud& cloud,
                       const pu::PointSource* source, const ArtifactWriteFn& write, core::JobContext& ctx,
                       int64_t memory_bytes, const TiledRun& tiled, SurfaceResult& result) {
  auto stat = [&](std::string name, double value) { result.statistics.emplace_back(std::move(name), value); };
  auto keep = [&](std::string name, std::string bytes) { result.kept.emplace_back(std::move(name), std::move(bytes)); };
  auto extracted =
      m.run(params, cloud, ctx, MethodRun{stat, keep, memory_bytes, source, write, &result.mesh_parts, tiled});
  if (!extracted.ok()) return extracted.status();
  result.mesh = std::move(extracted->mesh);
  if (result.mesh_parts > 0) return absl::OkStatus();  // Its statistics are the parts' (RunTiledPu).
  if (result.mesh.faces.empty()) {
    return absl::FailedPreconditionError("no surface was found: the points may be too sparse for the chosen spacing");
  }
  AddMeshStatistics(result.mesh, extracted->stats, &result.statistics);
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<SurfaceResult> ReconstructSurface(const std::string& method, const core::ParamSet& params,
                                                 core::PointCloud cloud, core::JobContext& ctx, int64_t memory_bytes,
                                                 const TiledRun& tiled) {
  auto m = CheckedMethod(method, params);
  if (!m.ok()) return m.status();
  const PointParams& points = *(*m)->points(params);
  SurfaceResult result;
  result.statistics.emplace_back("input_points", static_cast<double>(cloud.size()));
  const auto normals_share = PrepareSurfaceCloud(points, cloud, ctx, result.statistics);
  if (!normals_share.ok()) return normals_share.status();

  core::SubContext engine_ctx(ctx, method, *normals_share, 0.98);
  LSQSURF_RETURN_IF_ERROR(RunMethod(**m, params, cloud, nullptr, nullptr, engine_ctx, memory_bytes, tiled, result));
  if (result.mesh_parts == 0) {
    core::SubContext fill_ctx(ctx, "filling holes", 0.98, 0.99);
    LSQSURF_RETURN_IF_ERROR(CloseHolesOnRequest(points, cloud, fill_ctx, result.mesh, result.statistics));
    if (points.fill_holes) {
      AddStatistic(&result.statistics, "triangles", static_cast<double>(result.mesh.faces.size()));
      AddStatistic(&result.statistics, "vertices", static_cast<double>(result.mesh.vertices.size()));
    }
    core::SubContext carry_ctx(ctx, "carrying the points' attributes", 0.99, 1.0);
    LSQSURF_RETURN_IF_ERROR(CarryPointAttributes(points, cloud, carry_ctx, result.mesh, result.statistics));
  }
  return result;
}

absl::StatusOr<SurfaceResult> ReconstructStreamed(const std::string& method, const core::ParamSet& params,
                                                  const pu::PointSource& source, int64_t points, core::JobContext& ctx,
                                                  int64_t memory_bytes, const ArtifactWriteFn& write,
                                                  const TiledRun& tiled) {
  auto m = CheckedMethod(method, params);
  if (!m.ok()) return m.status();
  if (!(*m)->streams) return absl::InvalidArgumentError(core::StrCat("'", method, "' cannot stream a cloud"));
  if ((*m)->points(params)->fill_holes) {
    return absl::InvalidArgumentError(
        "fill_holes needs the whole mesh in memory, and a cloud this large is delivered in parts; leave "
        "fill_holes off, or split the cloud");
  }
  SurfaceResult result;
  result.statistics.emplace_back("input_points", static_cast<double>(points));
  result.statistics.emplace_back("input_streamed", 1);
  core::SubContext engine_ctx(ctx, method, 0.0, 1.0);
  LSQSURF_RETURN_IF_ERROR(
      RunMethod(**m, params, core::PointCloud{}, &source, write, engine_ctx, memory_bytes, tiled, result));
  return result;
}

void AddMeshStatistics(const core::TriangleMesh& mesh, const extract::IsosurfaceStats& extraction,
                       Statistics* statistics) {
  auto stat = [&](std::string name, double value) { statistics->emplace_back(std::move(name), value); };
  // The topology statistics are the delivered mesh's (EncodeResultMesh).
  stat("triangles", static_cast<double>(mesh.faces.size()));
  stat("vertices", static_cast<double>(mesh.vertices.size()));
  stat("cells_visited", static_cast<double>(extraction.cells_visited));
  // Why a surface can come back open: triangles at roots where the method does not trust F.
  if (extraction.rejected_polygons > 0) stat("untrusted_triangles", static_cast<double>(extraction.rejected_polygons));
  if (extraction.filled_holes > 0) stat("filled_holes", static_cast<double>(extraction.filled_holes));
  if (extraction.corner_specks > 0) stat("corner_specks", static_cast<double>(extraction.corner_specks));
  if (extraction.pierced_corners > 0) stat("pierced_corners", static_cast<double>(extraction.pierced_corners));
  if (extraction.corners_left_coarse > 0) stat("corners_left_coarse", 1);
  if (extraction.creases_left_coarse > 0) stat("creases_left_coarse", 1);
  if (extraction.topology_checks > 0) stat("topology_checks", 1);
  if (extraction.wall_splits > 0) stat("wall_splits", static_cast<double>(extraction.wall_splits));
  if (extraction.tree_seconds > 0) stat("tree_seconds", extraction.tree_seconds);
  stat("tracking_seconds", extraction.tracking_seconds);
  stat("marching_seconds", extraction.marching_seconds);
  if (extraction.crease_seconds > 0) stat("crease_seconds", extraction.crease_seconds);
  if (extraction.relax_seconds > 0) stat("relax_seconds", extraction.relax_seconds);
  const core::TriangleQuality quality = core::MeasureTriangleQuality(mesh);
  stat("min_angle_p1", quality.min_angle_p1);
  stat("min_angle_median", quality.min_angle_median);
  stat("aspect_ratio_p99", quality.aspect_ratio_p99);
  // The smallest-angle histogram as shares of the faces, one statistic per 5° bin.
  const double faces = std::max<double>(1, static_cast<double>(mesh.faces.size()));
  for (size_t bin = 0; bin < quality.min_angle_histogram.size(); ++bin) {
    const int from = static_cast<int>(bin) * core::TriangleQuality::kBinDegrees;
    stat(core::StrCat("min_angle_share_", from, "_", from + core::TriangleQuality::kBinDegrees),
         static_cast<double>(quality.min_angle_histogram[bin]) / faces);
  }
}

absl::StatusOr<std::string> EncodeResultMesh(const core::TriangleMesh& mesh, int position_bits, Statistics* statistics,
                                             const core::JobContext* ctx) {
  const auto start = std::chrono::steady_clock::now();
  const auto check = [ctx] { return ctx != nullptr ? ctx->CheckCancelled() : absl::OkStatus(); };
  const int64_t distinct = core::CountDistinctPositions(mesh.vertices);
  io::DracoOptions draco;
  draco.position_bits = position_bits > 0 ? position_bits : io::FewestPositionBits(mesh, distinct);
  LSQSURF_RETURN_IF_ERROR(check());
  auto encoded = io::EncodeDracoMesh(mesh, draco);
  if (!encoded.ok()) return encoded.status();
  LSQSURF_RETURN_IF_ERROR(check());
  // What a client decodes, merged by position, is what the statistics describe. When the round trip keeps every
  // position of a mesh without coincident vertices apart, merging changes nothing and that is the engine's mesh
  // itself; otherwise the bytes are decoded and merged.
  core::MeshTopology topo;
  const bool kept = io::DistinctAfterQuantization(mesh.vertices, draco.position_bits) >= distinct;
  if (kept && distinct == static_cast<int64_t>(mesh.vertices.size())) {
    topo = core::AnalyzeTopology(mesh);
  } else {
    const auto decode = [](const std::string& bytes) -> absl::StatusOr<core::TriangleMesh> {
      auto decoded = io::DecodeDracoMesh(bytes);
      if (decoded.ok()) return decoded;
      return absl::InternalError(core::StrCat("the result mesh does not decode: ", decoded.status().message()));
    };
    auto delivered = decode(*encoded);
    if (!delivered.ok()) return delivered.status();
    // Vertices the quantization (or the engine) put together are merged as a client's weld would, and the faces
    // that then collapse or lie on one another go, so that what is delivered stays manifold; the merged mesh is
    // sent instead.
    const size_t before = delivered->vertices.size();
    const int64_t dropped = core::MergeCoincidentVertices(*delivered);
    if (dropped > 0 || delivered->vertices.size() != before) {
      spdlog::info("result mesh: {} vertices merged at {} bits, {} faces dropped", before - delivered->vertices.size(),
                   draco.position_bits, dropped);
      LSQSURF_RETURN_IF_ERROR(check());
      encoded = io::EncodeDracoMesh(*delivered, draco);
      if (!encoded.ok()) return encoded.status();
      delivered = decode(*encoded);
      if (!delivered.ok()) return delivered.status();
    }
    LSQSURF_RETURN_IF_ERROR(check());
    AddStatistic(statistics, "delivery_dropped_faces", static_cast<double>(dropped));
    topo = core::AnalyzeTopology(core::WeldByPosition(*delivered));
  }
  AddStatistic(statistics, "delivered_position_bits", draco.position_bits);
  AddStatistic(statistics, "boundary_edges", static_cast<double>(topo.boundary_edges));
  AddStatistic(statistics, "non_manifold_edges", static_cast<double>(topo.non_manifold_edges));
  AddStatistic(statistics, "degenerate_faces", static_cast<double>(topo.degenerate_faces));
  AddStatistic(statistics, "components", static_cast<double>(topo.components));
  AddStatistic(statistics, "encode_seconds", core::SecondsSince(start));
  return encoded;
}

}  // namespace lsqsurf::jobs
