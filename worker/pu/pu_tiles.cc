#include "worker/pu/pu_tiles.h"

#include <algorithm>
#include <cmath>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/pu/pu_internal.h"

namespace lsqsurf::pu {

const core::ParamTable<PuTileParams>& PuTileParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuTileParams>();
    t->Integer<&PuTileParams::tile_points>("tile_points", 1000, 1'000'000'000, "points",
                                           "clouds of more points are reconstructed tile by tile, each tile holding "
                                           "at most this many; memory per tile follows it");
    t->Real<&PuTileParams::support_cap>(
        "support_cap", 8, 512, "mean point spacings",
        "largest support radius of a tiled build; fitting balls grow no farther; tile margins are about 2 of these");
    return t;
  }();
  return *table;
}

namespace {

// Deepest level the tiles may have: 2^30 cells per axis keep the keys in 64 bits.
constexpr int kMaxTileLevel = 20;

struct TileGrid {
  core::Vec3d origin;
  double edge = 0;
  int level = 0;
  int64_t cells = 1;  // Per axis.

  std::array<int64_t, 3> CellOf(const core::Vec3d& p) const {
    std::array<int64_t, 3> c{};
    for (int k = 0; k < 3; ++k) {
      c[static_cast<size_t>(k)] =
          std::clamp<int64_t>(static_cast<int64_t>(std::floor((p[k] - origin[k]) / edge)), 0, cells - 1);
    }
    return c;
  }
  uint64_t Key(const std::array<int64_t, 3>& c) const {
    return static_cast<uint64_t>(c[0]) | static_cast<uint64_t>(c[1]) << 21 | static_cast<uint64_t>(c[2]) << 42;
  }
  std::array<int64_t, 3> FromKey(uint64_t key) const {
    constexpr uint64_t kMask = (uint64_t{1} << 21) - 1;
    return {static_cast<int64_t>(key & kMask), static_cast<int64_t>(key >> 21 & kMask),
            static_cast<int64_t>(key >> 42)};
  }
  // Computed from the integer corner alone, so that neighbours agree on their common side.
  core::Box3 Cube(const std::array<int64_t, 3>& c) const {
    const core::Vec3d lo =
        origin + edge * core::Vec3d(static_cast<double>(c[0]), static_cast<double>(c[1]), static_cast<double>(c[2]));
    const core::Vec3d hi = origin + edge * core::Vec3d(static_cast<double>(c[0] + 1), static_cast<double>(c[1] + 1),
                                                       static_cast<double>(c[2] + 1));
    return core::Box3(lo, hi);
  }
  // Calls visit(key) for every cell whose cube grown by `reach` holds p.
  template <typename Visit>
  void ForEachCellNear(const core::Vec3d& p, double reach, Visit&& visit) const {
    const auto lo = CellOf(p - core::Vec3d::Constant(reach));
    const auto hi = CellOf(p + core::Vec3d::Constant(reach));
    for (int64_t z = lo[2]; z <= hi[2]; ++z)
      for (int64_t y = lo[1]; y <= hi[1]; ++y)
        for (int64_t x = lo[0]; x <= hi[0]; ++x) visit(Key({x, y, z}));
  }
};

// The shallowest level of the fitting octree at which no cube holds more than `tile_points`.
TileGrid ChooseTiles(const core::PointCloud& cloud, const PuFrame& frame, int64_t tile_points) {
  TileGrid grid{frame.origin, frame.root_edge, 0, 1};
  while (grid.level < kMaxTileLevel) {
    int64_t largest = 0;
    if (grid.level > 0) {
      absl::flat_hash_map<uint64_t, int64_t> counts;
      for (const core::Vec3f& p : cloud.positions) {
        largest = std::max(largest, ++counts[grid.Key(grid.CellOf(p.cast<double>()))]);
      }
    } else {
      largest = static_cast<int64_t>(cloud.size());
    }
    if (largest <= tile_points) break;
    ++grid.level;
    grid.edge /= 2;
    grid.cells *= 2;
  }
  return grid;
}

// Appends a tile's finished surface to the merged mesh, welding its border vertices to those the
// neighbouring tiles already gave (by lattice edge).
class TileWelder {
 public:
  void Add(TileSurface& tile) {
    const core::TriangleMesh& mesh = tile.surface.mesh;
    std::vector<uint32_t> index(mesh.vertices.size());
    if (merged_.vertex_attributes.empty()) {
      for (const core::ScalarAttribute& a : mesh.vertex_attributes) merged_.vertex_attributes.push_back({a.name, {}});
    }
    for (size_t v = 0; v < mesh.vertices.size(); ++v) {
      const uint64_t edge = tile.surface.trace.vertex_edges[v];
      if (tile.seam[v] && edge != 0) {
        const auto [it, inserted] = seam_.try_emplace(edge, static_cast<uint32_t>(merged_.vertices.size()));
        if (!inserted) {
          index[v] = it->second;
          ++shared_;
          continue;
        }
      }
      index[v] = static_cast<uint32_t>(merged_.vertices.size());
      merged_.vertices.push_back(mesh.vertices[v]);
      if (!mesh.normals.empty()) merged_.normals.push_back(mesh.normals[v]);
      for (size_t a = 0; a < merged_.vertex_attributes.size() && a < mesh.vertex_attributes.size(); ++a) {
        merged_.vertex_attributes[a].values.push_back(mesh.vertex_attributes[a].values[v]);
      }
    }
    for (core::Triangle t : mesh.faces) {
      for (uint32_t& v : t) v = index[v];
      merged_.faces.push_back(t);
    }
  }
  core::TriangleMesh& mesh() { return merged_; }
  int64_t shared() const { return shared_; }

 private:
  core::TriangleMesh merged_;
  absl::flat_hash_map<uint64_t, uint32_t> seam_;
  int64_t shared_ = 0;
};

void AddStats(const extract::IsosurfaceStats& tile, extract::IsosurfaceStats& sum) {
  sum.cells_visited += tile.cells_visited;
  sum.surface_cells += tile.surface_cells;
  sum.field_evaluations += tile.field_evaluations;
  sum.tetrahedra += tile.tetrahedra;
  sum.crossings += tile.crossings;
  sum.rejected_polygons += tile.rejected_polygons;
  sum.restored_triangles += tile.restored_triangles;
  sum.crease_vertices += tile.crease_vertices;
  sum.crease_corners += tile.crease_corners;
  sum.relaxed_vertices += tile.relaxed_vertices;
  sum.flipped_edges += tile.flipped_edges;
  sum.tree_seconds += tile.tree_seconds;
  sum.tracking_seconds += tile.tracking_seconds;
  sum.marching_seconds += tile.marching_seconds;
  sum.crease_seconds += tile.crease_seconds;
  sum.relax_seconds += tile.relax_seconds;
}

void AddFitStats(const PuStats& tile, PuStats& sum) {
  for (size_t d = 0; d < sum.fits_per_degree.size(); ++d) sum.fits_per_degree[d] += tile.fits_per_degree[d];
  sum.quadric_fits += tile.quadric_fits;
  sum.sharp_edges += tile.sharp_edges;
  sum.sharp_corners += tile.sharp_corners;
  sum.cells_examined += tile.cells_examined;
  sum.unmet_threshold += tile.unmet_threshold;
  sum.fit_seconds += tile.fit_seconds;
  sum.spacing_seconds += tile.spacing_seconds;
  sum.index_seconds += tile.index_seconds;
}

}  // namespace

absl::StatusOr<extract::IsosurfaceResult> ExtractTiled(const core::PointCloud& cloud, const PuFrame& frame,
                                                       const PuExtractParams& params, const PuTileParams& tiles,
                                                       core::JobContext& ctx, TiledStats* stats,
                                                       const std::function<void(const TilePart&)>& on_tile) {
  LSQSURF_RETURN_IF_ERROR(PuTileParamTable().Validate(tiles));
  LSQSURF_RETURN_IF_ERROR(PuExtractParamTable().Validate(params));
  TiledStats local_stats;
  TiledStats& s = stats != nullptr ? *stats : local_stats;
  s = {};
  const TileGrid grid = ChooseTiles(cloud, frame, tiles.tile_points);
  const double reach = ExtractionReach(frame.root_edge, frame.mean_spacing, params);
  // F over a tile and its extraction reach reads points within 2 max_support of that.
  s.margin = reach + 2 * frame.max_support * (1 + 1e-9);
  s.tile_level = grid.level;
  // Faces come from leaves near the data: within the reach of a point, or the coverage distance.
  const double near = reach + 1.25 * frame.max_support;
  absl::flat_hash_map<uint64_t, std::vector<uint32_t>> tile_points;
  absl::flat_hash_set<uint64_t> near_data;
  for (size_t i = 0; i < cloud.size(); ++i) {
    const core::Vec3d p = cloud.positions[i].cast<double>();
    grid.ForEachCellNear(p, near, [&](uint64_t key) { near_data.insert(key); });
  }
  for (size_t i = 0; i < cloud.size(); ++i) {
    const core::Vec3d p = cloud.positions[i].cast<double>();
    grid.ForEachCellNear(p, s.margin, [&](uint64_t key) {
      if (near_data.contains(key)) tile_points[key].push_back(static_cast<uint32_t>(i));
    });
  }
  std::vector<uint64_t> keys(near_data.begin(), near_data.end());
  std::sort(keys.begin(), keys.end());
  near_data = {};
  TileWelder welder;
  extract::IsosurfaceResult result;
  for (size_t t = 0; t < keys.size(); ++t) {
    core::SubContext tile_ctx(ctx, core::StrCat("tile ", t + 1, " of ", keys.size()),
                              static_cast<double>(t) / static_cast<double>(keys.size()),
                              static_cast<double>(t + 1) / static_cast<double>(keys.size()));
    std::vector<uint32_t> indices = std::move(tile_points[keys[t]]);
    tile_points.erase(keys[t]);
    ++s.tiles_examined;
    if (indices.size() < 4) continue;
    core::PointCloud part;
    part.positions.reserve(indices.size());
    part.normals.reserve(indices.size());
    for (uint32_t i : indices) {
      part.positions.push_back(cloud.positions[i]);
      part.normals.push_back(cloud.normals[i]);
    }
    indices = {};
    s.largest_tile = std::max(s.largest_tile, static_cast<int64_t>(part.size()));
    const core::Box3 cube = grid.Cube(grid.FromKey(keys[t]));
    const core::Box3 region(cube.min() - core::Vec3d::Constant(reach), cube.max() + core::Vec3d::Constant(reach));
    core::SubContext fit_ctx(tile_ctx, "fitting", 0.0, 0.5);
    auto function = BuildPuInFrame(part, frame, &region, fit_ctx);
    if (!function.ok() && absl::IsFailedPrecondition(function.status())) continue;  // No fit near it.
    if (!function.ok()) return function.status();
    part = {};
    AddFitStats((*function)->stats(), s.fit);
    core::SubContext extract_ctx(tile_ctx, "extracting", 0.5, 1.0);
    auto surface = ExtractTile(**function, params, cube, extract_ctx);
    if (!surface.ok()) return surface.status();
    function->reset();
    if (surface->surface.mesh.faces.empty()) continue;
    ++s.tiles;
    AddStats(surface->surface.stats, result.stats);
    const size_t first_face = welder.mesh().faces.size();
    welder.Add(*surface);
    if (on_tile) on_tile(TilePart{static_cast<int64_t>(t), &welder.mesh(), first_face});
  }
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  s.seam_vertices = welder.shared();
  s.fit.mean_spacing = frame.mean_spacing;
  s.fit.noise_estimate = frame.noise_estimate;
  s.fit.error_threshold = frame.params.error_threshold;
  s.fit.min_points = frame.params.min_points;
  s.fit.root_edge = frame.root_edge;
  result.mesh = std::move(welder.mesh());
  if (result.mesh.faces.empty()) return absl::FailedPreconditionError("no surface could be extracted from the tiles");
  return result;
}

}  // namespace lsqsurf::pu
