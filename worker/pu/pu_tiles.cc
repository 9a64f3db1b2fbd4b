#include "worker/pu/pu_tiles.h"

#include <algorithm>
#include <chrono>
#include <cmath>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/kd_tree.h"
#include "worker/core/noise.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/pu/pu_internal.h"
#include "worker/pu/tile_files.h"

namespace lsqsurf::pu {

const core::ParamTable<PuTileParams>& PuTileParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuTileParams>();
    t->Integer<&PuTileParams::tile_points>("tile_points", 1000, 1'000'000'000, "points",
                                           "clouds of more points are reconstructed tile by tile, each tile holding "
                                           "at most this many; memory per tile follows it");
    t->Real<&PuTileParams::support_cap>("support_cap", 16, 512, "mean point spacings",
                                        "largest support radius of a tiled build; fitting balls grow no farther; "
                                        "tile margins are about 2 of these");
    t->Real<&PuTileParams::threshold_spacings>("threshold_spacings", 0, 16, "mean point spacings",
                                               "on dense clouds error_threshold is at most this many mean point "
                                               "spacings, so that the fits are as fine as the points resolve; 0 "
                                               "keeps error_threshold at any density");
    return t;
  }();
  return *table;
}

absl::Status CloudSource::ForEachChunk(const std::function<absl::Status(const core::PointCloud&)>& visit) const {
  core::PointCloud chunk;
  for (size_t begin = 0; begin < cloud_.size(); begin += chunk_points_) {
    const size_t end = std::min(cloud_.size(), begin + chunk_points_);
    chunk.positions.assign(cloud_.positions.begin() + static_cast<ptrdiff_t>(begin),
                           cloud_.positions.begin() + static_cast<ptrdiff_t>(end));
    chunk.normals.clear();
    if (cloud_.has_normals()) {
      chunk.normals.assign(cloud_.normals.begin() + static_cast<ptrdiff_t>(begin),
                           cloud_.normals.begin() + static_cast<ptrdiff_t>(end));
    }
    LSQSURF_RETURN_IF_ERROR(visit(chunk));
  }
  return absl::OkStatus();
}

absl::Status MeshSink::AddTile(const TileOutput& tile) {
  if (tile.first_vertex + static_cast<int64_t>(tile.vertices.size()) > int64_t{UINT32_MAX}) {
    return absl::ResourceExhaustedError("the surface has more than 2^32 vertices; write it tile by tile");
  }
  mesh_.vertices.insert(mesh_.vertices.end(), tile.vertices.begin(), tile.vertices.end());
  mesh_.normals.insert(mesh_.normals.end(), tile.normals.begin(), tile.normals.end());
  if (mesh_.vertex_attributes.empty()) {
    for (const core::ScalarAttribute& a : tile.attributes) mesh_.vertex_attributes.push_back({a.name, {}});
  }
  for (size_t a = 0; a < mesh_.vertex_attributes.size() && a < tile.attributes.size(); ++a) {
    mesh_.vertex_attributes[a].values.insert(mesh_.vertex_attributes[a].values.end(), tile.attributes[a].values.begin(),
                                             tile.attributes[a].values.end());
  }
  for (const auto& f : tile.faces) {
    mesh_.faces.push_back({static_cast<uint32_t>(f[0]), static_cast<uint32_t>(f[1]), static_cast<uint32_t>(f[2])});
  }
  return absl::OkStatus();
}

namespace {

// Deepest level the tiles and the histogram may have (21-bit keys per axis).
constexpr int kMaxTileLevel = 20;
// The histogram's cells hold about this many points on a surface filling its bounding box.
constexpr double kHistogramCellPoints = 256;

struct Bounds {
  int64_t points = 0;
  core::Box3 box;
};

absl::StatusOr<Bounds> ScanBounds(const PointSource& source, core::JobContext& ctx) {
  Bounds bounds;
  LSQSURF_RETURN_IF_ERROR(source.ForEachChunk([&](const core::PointCloud& chunk) -> absl::Status {
    if (!chunk.has_normals()) return absl::InvalidArgumentError("PU surfaces need oriented normals");
    if (const int64_t bad = core::FindNonFinite(chunk.positions); bad >= 0) {
      return absl::InvalidArgumentError(
          core::StrCat("point ", bounds.points + bad, " has a coordinate that is not a finite number"));
    }
    bounds.box.extend(core::BoundingBox(chunk.positions));
    bounds.points += static_cast<int64_t>(chunk.size());
    return ctx.CheckCancelled();
  }));
  if (bounds.points < 4) return absl::InvalidArgumentError("PU surfaces need at least 4 points");
  if (!(core::Diagonal(bounds.box) > 0)) return absl::InvalidArgumentError("all points coincide");
  return bounds;
}

// The level whose cells hold about kHistogramCellPoints points of a surface as large as the
// bounding box's sides: fine enough to place tiles, coarse enough to keep few cells.
int HistogramLevel(const Bounds& bounds, double root_edge) {
  const core::Vec3d size = bounds.box.sizes();
  const double area = std::max(2 * (size.x() * size.y() + size.y() * size.z() + size.z() * size.x()),
                               size.maxCoeff() * size.maxCoeff());
  const double edge = std::sqrt(area * kHistogramCellPoints / static_cast<double>(bounds.points));
  return std::clamp(static_cast<int>(std::lround(std::log2(root_edge / edge))), 1, kMaxTileLevel);
}

absl::StatusOr<absl::flat_hash_map<uint64_t, int64_t>> Histogram(const PointSource& source, const TileGrid& grid,
                                                                 core::JobContext& ctx) {
  absl::flat_hash_map<uint64_t, int64_t> counts;
  LSQSURF_RETURN_IF_ERROR(source.ForEachChunk([&](const core::PointCloud& chunk) {
    for (const core::Vec3f& p : chunk.positions) ++counts[TileGrid::Key(grid.CellOf(p.cast<double>()))];
    return ctx.CheckCancelled();
  }));
  return counts;
}

// The shallowest level at which no cube holds more than `tile_points` (at most the histogram's).
int TileLevel(const absl::flat_hash_map<uint64_t, int64_t>& histogram, int histogram_level, int64_t tile_points) {
  for (int level = 0; level < histogram_level; ++level) {
    const int shift = histogram_level - level;
    absl::flat_hash_map<uint64_t, int64_t> counts;
    int64_t largest = 0;
    for (const auto& [key, count] : histogram) {
      auto c = TileGrid::FromKey(key);
      for (int64_t& v : c) v >>= shift;
      largest = std::max(largest, counts[TileGrid::Key(c)] += count);
    }
    if (largest <= tile_points) return level;
  }
  return histogram_level;
}

// The tiles' margins for a mean spacing: four coarse extraction cells for the J1a tree, and two
// support caps for the fits (BuildPuInFrame); and the reach of the data, within which a tile may
// own faces.
struct Margins {
  double max_support = 0;
  double extraction = 0;
  double data = 0;
  double near = 0;
};

Margins MarginsFor(double spacing, const PuFrame& frame, const PuParams& fit, const PuExtractParams& extract,
                   const PuTileParams& tiles) {
  Margins m;
  // Never below the support of the deepest cells, which cannot be split further.
  const double deepest_support = fit.support_factor * kSqrt3 * std::ldexp(frame.root_edge, -fit.max_depth);
  m.max_support = std::max(tiles.support_cap * spacing, deepest_support * (1 + 1e-9));
  m.extraction = ExtractionReach(frame.root_edge, spacing, extract);
  // A point is covered within coverage_factor local spacings of its nearest point, and local
  // spacings are capped at max_support: the nearest point must be in the tile when that decides,
  // and so must the points the rim test reads.
  const double covered = fit.coverage_factor * m.max_support;
  m.data = m.extraction + std::max(2 * m.max_support, kRimReadFactor * covered) * (1 + 1e-9);
  m.near = m.extraction + covered;
  return m;
}

// A weighted median: the value below which half the weight lies.
double WeightedMedian(std::vector<std::pair<double, double>> values) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  double total = 0;
  for (const auto& [value, weight] : values) total += weight;
  double below = 0;
  for (const auto& [value, weight] : values) {
    below += weight;
    if (below >= total / 2) return value;
  }
  return values.back().first;
}

// The tiles of `grid` near the data and their point files: every tile whose cube, grown by the
// data margin, holds a point, filled in one pass over the source.
struct Bucketed {
  std::vector<uint64_t> keys;  // Sorted.
  std::unique_ptr<TileBuckets> buckets;
};

absl::StatusOr<Bucketed> Bucket(const PointSource& source, const TileGrid& grid, const TileGrid& histogram_grid,
                                const absl::flat_hash_map<uint64_t, int64_t>& histogram, const Margins& margins,
                                const std::string& directory, core::JobContext& ctx) {
  absl::flat_hash_set<uint64_t> near;
  for (const auto& [key, count] : histogram) {
    grid.ForEachCellMeeting(histogram_grid.Cube(TileGrid::FromKey(key)), margins.near,
                            [&](uint64_t tile) { near.insert(tile); });
  }
  Bucketed out;
  out.keys.assign(near.begin(), near.end());
  std::sort(out.keys.begin(), out.keys.end());
  out.buckets = std::make_unique<TileBuckets>(directory, out.keys);
  LSQSURF_RETURN_IF_ERROR(source.ForEachChunk([&](const core::PointCloud& chunk) -> absl::Status {
    for (size_t i = 0; i < chunk.size(); ++i) {
      absl::Status status;
      grid.ForEachCellNear(chunk.positions[i].cast<double>(), margins.data, [&](uint64_t key) {
        if (status.ok()) status = out.buckets->Add(key, chunk.positions[i], chunk.normals[i]);
      });
      LSQSURF_RETURN_IF_ERROR(status);
    }
    return ctx.CheckCancelled();
  }));
  LSQSURF_RETURN_IF_ERROR(out.buckets->Flush());
  return out;
}

// The mean nearest-neighbour distance and the scan noise, measured on an even sample of the data:
// the histogram cells whose key hashes to 0 modulo kProbeShare (every cell when a tile has none),
// with their neighbourhood of half a cell. Both are statistics of the whole cloud, fixed once for
// every tile; a sample of an eighth of the surface measures them within a fraction of a percent
// at an eighth of the cost (the kd-trees and queries of every point took longer than reading and
// bucketing the cloud).
constexpr uint64_t kProbeShare = 8;

bool IsProbeCell(uint64_t key) { return ((key * 0x9E3779B97F4A7C15ull) >> 32) % kProbeShare == 0; }

// The probe cells of a tile's histogram cells: its hashed share, or all of them where that is none.
absl::flat_hash_set<uint64_t> ProbeCellsAmong(std::span<const uint64_t> cells) {
  absl::flat_hash_set<uint64_t> probe_cells;
  for (uint64_t key : cells) {
    if (IsProbeCell(key)) probe_cells.insert(key);
  }
  if (probe_cells.empty()) probe_cells.insert(cells.begin(), cells.end());
  return probe_cells;
}

struct Measured {
  double mean_spacing = 0;
  core::NoiseEstimate noise;
};

struct ProbeSums {
  double distance_sum = 0;
  int64_t probes = 0;
  std::vector<std::pair<double, double>> sigmas, balls;  // Weighted by probes.
};

// One tile's share: its points near probe cells, the nearest-neighbour distance of those inside
// them, and the noise of that sample.
absl::Status MeasureTile(const core::PointCloud& cloud, const core::Box3& cube, const TileGrid& histogram_grid,
                         const absl::flat_hash_set<uint64_t>& probe_cells, double known_sigma, ProbeSums& sums,
                         core::JobContext& ctx) {
  const double reach = histogram_grid.edge / 2;
  core::PointCloud sample;
  std::vector<char> probe;
  for (size_t i = 0; i < cloud.size(); ++i) {
    const core::Vec3d p = cloud.positions[i].cast<double>();
    bool near = false;
    histogram_grid.ForEachCellNear(p, reach, [&](uint64_t key) { near = near || probe_cells.contains(key); });
    if (!near) continue;
    sample.positions.push_back(cloud.positions[i]);
    sample.normals.push_back(cloud.normals[i]);
    const bool owned = InHalfOpenBox(cube, p);
    probe.push_back(owned && probe_cells.contains(TileGrid::Key(histogram_grid.CellOf(p))));
  }
  if (sample.size() < 2) return absl::OkStatus();
  const core::KdTree tree(sample.positions);
  std::vector<double> distance(sample.size(), -1);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      sample.size(), 4096,
      [&](size_t b, size_t e) {
        std::vector<core::Neighbor> knn;
        for (size_t i = b; i < e; ++i) {
          if (!probe[i]) continue;
          tree.Knn(sample.positions[i], 2, knn);
          distance[i] = std::sqrt(static_cast<double>(knn.back().distance2));
        }
      },
      &ctx));
  int64_t probes = 0;
  for (double d : distance) {
    if (d < 0) continue;
    sums.distance_sum += d;
    ++probes;
  }
  if (probes == 0) return absl::OkStatus();
  sums.probes += probes;
  const core::NoiseEstimate noise = core::EstimateNoise(tree, sample.normals, known_sigma);
  sums.sigmas.emplace_back(noise.sigma, static_cast<double>(probes));
  sums.balls.emplace_back(noise.points_in_ball, static_cast<double>(probes));
  return absl::OkStatus();
}

absl::StatusOr<Measured> MeasuredFrom(ProbeSums sums, double known_sigma) {
  if (sums.probes == 0) return absl::InvalidArgumentError("the points have no spacing to size cells by");
  Measured m;
  m.mean_spacing = sums.distance_sum / static_cast<double>(sums.probes);
  m.noise.sigma = known_sigma >= 0 ? known_sigma : WeightedMedian(std::move(sums.sigmas));
  m.noise.points_in_ball = WeightedMedian(std::move(sums.balls));
  return m;
}

absl::StatusOr<Measured> MeasureTiles(const Bucketed& tiles, const TileGrid& grid, const TileGrid& histogram_grid,
                                      const absl::flat_hash_map<uint64_t, int64_t>& histogram, double known_sigma,
                                      core::JobContext& ctx) {
  // The histogram cells of each tile, whose probe cells it measures.
  absl::flat_hash_map<uint64_t, std::vector<uint64_t>> cells_of_tile;
  for (const auto& [key, count] : histogram) {
    const core::Box3 cell = histogram_grid.Cube(TileGrid::FromKey(key));
    cells_of_tile[TileGrid::Key(grid.CellOf(cell.center()))].push_back(key);
  }
  ProbeSums sums;
  for (size_t t = 0; t < tiles.keys.size(); ++t) {
    const auto cells = cells_of_tile.find(tiles.keys[t]);
    if (cells == cells_of_tile.end()) continue;
    const absl::flat_hash_set<uint64_t> probe_cells = ProbeCellsAmong(cells->second);
    const core::Box3 cube = grid.Cube(TileGrid::FromKey(tiles.keys[t]));
    const core::Vec3d reach = core::Vec3d::Constant(histogram_grid.edge);
    const core::Box3 needed(cube.min() - reach, cube.max() + reach);
    auto cloud = tiles.buckets->Read(tiles.keys[t], &needed);
    if (!cloud.ok()) return cloud.status();
    LSQSURF_RETURN_IF_ERROR(MeasureTile(*cloud, cube, histogram_grid, probe_cells, known_sigma, sums, ctx));
    ctx.ReportProgress("measuring the tiles", static_cast<double>(t + 1) / static_cast<double>(tiles.keys.size()));
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  }
  return MeasuredFrom(std::move(sums), known_sigma);
}

// What the frame takes from the measures and the margins.
void FixFrame(const Measured& measured, const Margins& margins, const PuParams& fit, const PuTileParams& tiles,
              PuFrame& frame) {
  frame.mean_spacing = measured.mean_spacing;
  // A fixed threshold on a cloud far denser than it leaves detail the points resolve to the
  // fits' tolerance (measured on spot at 32M: Chamfer 3.95e-6 at 2e-4, 2.01e-6 at 1e-4).
  PuParams bounded = fit;
  // Rounded down to a step of 1/16 octave (4.4 %): the measured spacing moves by about 1e-3 with
  // the tile cut, and the threshold should not.
  const double spacing_bound =
      tiles.threshold_spacings > 0
          ? std::exp2(std::floor(16 * std::log2(tiles.threshold_spacings * measured.mean_spacing / frame.diagonal)) /
                      16)
          : 0;
  if (tiles.threshold_spacings > 0 && spacing_bound < bounded.error_threshold) {
    bounded.error_threshold = std::max(spacing_bound, kMinErrorThreshold);
  }
  PuStats effective;
  frame.params = EffectiveParams(bounded, measured.noise, frame.diagonal, effective);
  frame.noise_estimate = effective.noise_estimate;
  frame.max_support = margins.max_support;
}

absl::Status ValidateTiledParams(const PuParams& fit, const PuExtractParams& extract, const PuTileParams& tiles) {
  LSQSURF_RETURN_IF_ERROR(Validate(fit));
  LSQSURF_RETURN_IF_ERROR(PuTileParamTable().Validate(tiles));
  return PuExtractParamTable().Validate(extract);
}

}  // namespace

struct PlannedCloud::Files {
  ScratchDir scratch;
  std::unique_ptr<TileBuckets> buckets;
};

PlannedCloud::PlannedCloud(TilePlan plan, std::unique_ptr<Files> files)
    : plan_(std::move(plan)), files_(std::move(files)) {}
PlannedCloud::~PlannedCloud() = default;

absl::StatusOr<core::PointCloud> PlannedCloud::TilePoints(size_t index) const {
  if (index >= plan_.tiles.size()) {
    return absl::OutOfRangeError(core::StrCat("tile ", index, " of a plan of ", plan_.tiles.size()));
  }
  const TileGrid grid = TileGrid::AtLevel(plan_.frame.origin, plan_.frame.root_edge, plan_.tile_level);
  const core::Box3 cube = grid.Cube(TileGrid::FromKey(plan_.tiles[index]));
  // The bucket's margin was sized by the first spacing estimate: only the exact one is read.
  const core::Vec3d data = core::Vec3d::Constant(plan_.data_margin);
  const core::Box3 needed(cube.min() - data, cube.max() + data);
  return files_->buckets->Read(plan_.tiles[index], &needed);
}

absl::StatusOr<std::unique_ptr<PlannedCloud>> PlannedCloud::Plan(const PointSource& source, const PuParams& fit,
                                                                 const PuExtractParams& extract,
                                                                 const PuTileParams& tiles, core::JobContext& ctx,
                                                                 const std::string& scratch_parent) {
  LSQSURF_RETURN_IF_ERROR(ValidateTiledParams(fit, extract, tiles));
  const auto start = std::chrono::steady_clock::now();
  TilePlan plan;
  const auto bounds = ScanBounds(source, ctx);
  if (!bounds.ok()) return bounds.status();
  plan.points = bounds->points;
  plan.extract = extract;
  PuFrame& frame = plan.frame;
  frame.diagonal = core::Diagonal(bounds->box);
  RootCube(bounds->box, frame.origin, frame.root_edge);
  const int histogram_level = HistogramLevel(*bounds, frame.root_edge);
  const TileGrid histogram_grid = TileGrid::AtLevel(frame.origin, frame.root_edge, histogram_level);
  auto histogram = Histogram(source, histogram_grid, ctx);
  if (!histogram.ok()) return histogram.status();
  const TileGrid grid =
      TileGrid::AtLevel(frame.origin, frame.root_edge, TileLevel(*histogram, histogram_level, tiles.tile_points));
  plan.tile_level = grid.level;
  // A first spacing from the histogram: the area of its occupied cells over the points. It
  // overestimates the mean nearest-neighbour distance, so margins sized by it hold.
  double spacing =
      histogram_grid.edge * std::sqrt(static_cast<double>(histogram->size()) / static_cast<double>(bounds->points));
  auto scratch = ScratchDir::Create(scratch_parent);
  if (!scratch.ok()) return scratch.status();
  const double known_sigma = fit.noise_level >= 0 ? fit.noise_level * frame.diagonal : -1.0;
  Bucketed bucketed;
  Measured measured;
  Margins margins;
  for (int attempt = 0;; ++attempt) {
    const Margins bucketed_for = MarginsFor(spacing, frame, fit, extract, tiles);
    auto b = Bucket(source, grid, histogram_grid, *histogram, bucketed_for, scratch->path(), ctx);
    if (!b.ok()) return b.status();
    bucketed = std::move(*b);
    plan.scan_seconds = core::SecondsSince(start) - plan.spacing_seconds;
    const auto spacing_start = std::chrono::steady_clock::now();
    auto m = MeasureTiles(bucketed, grid, histogram_grid, *histogram, known_sigma, ctx);
    plan.spacing_seconds += core::SecondsSince(spacing_start);
    if (!m.ok()) return m.status();
    measured = *m;
    margins = MarginsFor(measured.mean_spacing, frame, fit, extract, tiles);
    if (margins.data <= bucketed_for.data && margins.near <= bucketed_for.near) break;
    if (attempt == 2) return absl::InternalError("the tiles' margins do not settle");
    LSQSURF_RETURN_IF_ERROR(bucketed.buckets->Clear());
    spacing = 1.1 * measured.mean_spacing;
  }
  histogram->clear();
  FixFrame(measured, margins, fit, tiles, frame);
  plan.data_margin = margins.data;
  plan.extraction_margin = margins.extraction;
  plan.tiles = std::move(bucketed.keys);
  plan.scratch_bytes = bucketed.buckets->TotalBytes();
  plan.measure_seconds = core::SecondsSince(start);
  auto files = std::make_unique<Files>(Files{*std::move(scratch), std::move(bucketed.buckets)});
  return std::unique_ptr<PlannedCloud>(new PlannedCloud(std::move(plan), std::move(files)));
}

absl::StatusOr<PuFrame> MeasureFrame(const core::PointCloud& cloud, const PuParams& fit, const PuExtractParams& extract,
                                     const PuTileParams& tiles, core::JobContext& ctx) {
  LSQSURF_RETURN_IF_ERROR(ValidateTiledParams(fit, extract, tiles));
  const CloudSource source(cloud);
  const auto bounds = ScanBounds(source, ctx);
  if (!bounds.ok()) return bounds.status();
  PuFrame frame;
  frame.diagonal = core::Diagonal(bounds->box);
  RootCube(bounds->box, frame.origin, frame.root_edge);
  const TileGrid histogram_grid =
      TileGrid::AtLevel(frame.origin, frame.root_edge, HistogramLevel(*bounds, frame.root_edge));
  const auto histogram = Histogram(source, histogram_grid, ctx);
  if (!histogram.ok()) return histogram.status();
  // As MeasureTiles measures the one tile of a plan whose tile is the root cube.
  std::vector<uint64_t> cells;
  cells.reserve(histogram->size());
  for (const auto& [key, count] : *histogram) cells.push_back(key);
  const absl::flat_hash_set<uint64_t> probe_cells = ProbeCellsAmong(cells);
  const double known_sigma = fit.noise_level >= 0 ? fit.noise_level * frame.diagonal : -1.0;
  const TileGrid one_tile = TileGrid::AtLevel(frame.origin, frame.root_edge, 0);
  const core::Box3 root = one_tile.Cube(one_tile.CellOf(bounds->box.center()));
  ProbeSums sums;
  LSQSURF_RETURN_IF_ERROR(MeasureTile(cloud, root, histogram_grid, probe_cells, known_sigma, sums, ctx));
  const auto measured = MeasuredFrom(std::move(sums), known_sigma);
  if (!measured.ok()) return measured.status();
  FixFrame(*measured, MarginsFor(measured->mean_spacing, frame, fit, extract, tiles), fit, tiles, frame);
  return frame;
}

absl::StatusOr<TiledStats> ReconstructTiled(const PointSource& source, const PuParams& fit,
                                            const PuExtractParams& extract, const PuTileParams& tiles,
                                            SurfaceSink& sink, core::JobContext& ctx,
                                            const std::string& scratch_parent) {
  core::SubContext measure_ctx(ctx, "measuring the cloud", 0.0, 0.15);
  auto planned = PlannedCloud::Plan(source, fit, extract, tiles, measure_ctx, scratch_parent);
  if (!planned.ok()) return planned.status();
  const TilePlan& plan = (*planned)->plan();
  TileJoiner joiner(plan, sink);
  core::SubContext tiles_ctx(ctx, "fitting and extracting tiles", 0.15, 1.0);
  const double count = static_cast<double>(plan.tiles.size());
  for (size_t t = 0; t < plan.tiles.size(); ++t) {
    core::SubContext tile_ctx(tiles_ctx, core::StrCat("tile ", t + 1, " of ", plan.tiles.size()),
                              static_cast<double>(t) / count, static_cast<double>(t + 1) / count);
    auto points = (*planned)->TilePoints(t);
    if (!points.ok()) return points.status();
    auto part = RunTile(plan, t, *std::move(points), tile_ctx);
    if (!part.ok()) return part.status();
    LSQSURF_RETURN_IF_ERROR(joiner.Add(*part));
  }
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  return joiner.Finish();
}

}  // namespace lsqsurf::pu
