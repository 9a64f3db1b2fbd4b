// worker/pu/pu_tiles.h — PU surfaces built and extracted tile by tile, seamless by construction.
//
// A partition of unity is local: F near a point depends only on the fits whose support holds
// it, and each fit only on the points near its cell. A tiled build fixes what is global once
// (the frame: root cube, diagonal, mean spacing, noise and the effective parameters) and bounds
// every support by `max_support`, so that a cell's decisions read only points within
// 2 × max_support of the region its support meets. A tile (a cube of the fitting octree) then
// builds F from the points within its margin and gets, over its cube, the whole cloud's F to the
// last bit; its J1a extraction tree, grown over the cube and ExtractionReach, has the whole
// tree's leaves inside the cube. Each tile keeps the faces of the leaves centred in its cube:
// the raw marching is the untiled one, face for face, and neighbouring tiles share the vertices
// on their common border, named by their lattice edges. Creases and relaxation run per tile with
// those border vertices fixed, so the welded mesh is closed across every seam.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"
#include "worker/extract/isosurface.h"
#include "worker/pu/pu.h"

namespace lsqsurf::pu {

struct PuTileParams {
  // A cloud of more points than this is reconstructed in tiles, cubes of the fitting octree small
  // enough to hold at most this many points each (their margins add about a third on a surface).
  // Memory per tile follows it (about 2 KB a point for build and extraction).
  int64_t tile_points = 4'000'000;
  // The largest support radius of a tiled build, in mean point spacings (16..512). Larger cells
  // are split without a fit and no fitting ball grows past it; margins are 2 of these (or
  // coverage_factor of these, if more) plus four coarse extraction cells.
  double support_cap = 64;
  // On dense clouds the error threshold follows the sampling: it is at most this many mean point
  // spacings (as a share of the diagonal), so that the fits are as fine as the points resolve
  // (0..16; 0 keeps error_threshold at any density). The default leaves clouds of a few million
  // points on a compact shape at error_threshold: it lowers it from about 8M points on the bunny
  // and 13M on spot (1.25e-4 at 32M on spot).
  double threshold_spacings = 1.25;
};

const core::ParamTable<PuTileParams>& PuTileParamTable();

// What a tiled build fixes for every tile.
struct PuFrame {
  core::Vec3d origin = core::Vec3d::Zero();  // The fitting octree's root cube.
  double root_edge = 0;
  double diagonal = 0;        // Of the whole cloud's bounding box.
  double mean_spacing = 0;    // Mean nearest-neighbour distance.
  double noise_estimate = 0;  // σ, share of the diagonal.
  PuParams params;            // After the density and noise adjustments.
  double max_support = 0;     // Model units.
};

// How a fit sums over its neighbours: in an order of the points alone (kCanonical), so that a
// tile's sums are the whole cloud's to the last bit, or in the kd-tree's (kAsFound: 15 % less
// fitting time on a noisy 100k-point bunny; the function then differs from the tiles' by rounding).
enum class SumOrder { kCanonical, kAsFound };

// F of `cloud` in `frame`: with `region`, exact over it (equal to the build over the whole cloud)
// when `cloud` holds every point within 2 × max_support of it (and within coverage_factor ×
// max_support, the coverage test's reach, where that is more); cells whose supports cannot reach
// it are not grown. Errors: as BuildPu.
absl::StatusOr<std::unique_ptr<PuFunction>> BuildPuInFrame(const core::PointCloud& cloud, const PuFrame& frame,
                                                           const core::Box3* region, core::JobContext& ctx,
                                                           SumOrder order = SumOrder::kCanonical);

// The frame a plan of `cloud` in one tile fixes (PlannedCloud::Plan with tile_points at least
// its size), measured in memory: an untiled build in it is the tiled builds' surface. Errors: as
// PlannedCloud::Plan.
absl::StatusOr<PuFrame> MeasureFrame(const core::PointCloud& cloud, const PuParams& fit, const PuExtractParams& extract,
                                     const PuTileParams& tiles, core::JobContext& ctx);

// A cloud read in chunks, as many times as asked: the parts of an upload, a file, a sampler.
class PointSource {
 public:
  virtual ~PointSource() = default;
  // Calls `visit` with successive chunks of oriented points, the same chunks in the same order on
  // every call; stops at the first error `visit` returns.
  virtual absl::Status ForEachChunk(const std::function<absl::Status(const core::PointCloud&)>& visit) const = 0;
};

// A cloud in memory, in chunks of `chunk_points`.
class CloudSource final : public PointSource {
 public:
  explicit CloudSource(const core::PointCloud& cloud, size_t chunk_points = 1 << 20)
      : cloud_(cloud), chunk_points_(chunk_points) {}
  absl::Status ForEachChunk(const std::function<absl::Status(const core::PointCloud&)>& visit) const override;

 private:
  const core::PointCloud& cloud_;
  size_t chunk_points_;
};

// One tile's part of the welded surface: the vertices first seen in this tile (their numbers in
// the whole mesh follow on from the previous tile's) and its faces in the whole mesh's numbers.
struct TileOutput {
  int64_t tile = 0;          // In the order the tiles ran.
  int64_t first_vertex = 0;  // The whole mesh's number of vertices[0].
  std::span<const core::Vec3f> vertices;
  std::span<const core::Vec3f> normals;  // Empty, or one per vertex.
  std::span<const core::ScalarAttribute> attributes;
  std::span<const std::array<int64_t, 3>> faces;
};

// Receives the surface tile by tile (a file writer, a result store, a mesh in memory).
class SurfaceSink {
 public:
  virtual ~SurfaceSink() = default;
  virtual absl::Status AddTile(const TileOutput& tile) = 0;
};

// Collects the tiles into one mesh. Errors: kResourceExhausted past 2^32 vertices.
class MeshSink final : public SurfaceSink {
 public:
  absl::Status AddTile(const TileOutput& tile) override;
  core::TriangleMesh& mesh() { return mesh_; }

 private:
  core::TriangleMesh mesh_;
};

struct TiledStats {
  PuFrame frame;
  int64_t points = 0;
  int64_t tiles = 0;           // Tiles that made faces.
  int64_t tiles_examined = 0;  // Tiles near the data.
  int tile_level = 0;          // Of the fitting octree.
  int64_t largest_tile = 0;    // Points one tile read, its margin included.
  int64_t seam_vertices = 0;   // Vertices two or more tiles shared.
  int64_t vertices = 0, faces = 0;
  double margin = 0;                 // Model units.
  int64_t scratch_bytes = 0;         // The tiles' point files.
  double measure_seconds = 0;        // Bounds, tiles, bucketing, spacing and noise; of which
  double scan_seconds = 0;           //   the passes over the source (bounds, histogram, buckets),
  double spacing_seconds = 0;        //   and the spacing and noise over the tiles.
  PuStats fit;                       // Summed over the tiles (fits of margins counted once per tile).
  extract::IsosurfaceStats extract;  // Summed over the tiles.
};

// A tiled build in three steps, so that its tiles can run apart (on other workers, on other
// servers): PlannedCloud fixes the frame and the tiles and buckets the points; RunTile makes one
// tile's part of the surface from that tile's points alone; TileJoiner welds the parts, taken in
// the plan's order, into the surface. ReconstructTiled is the three in one process.
struct TilePlan {
  PuFrame frame;
  PuExtractParams extract;
  int tile_level = 0;            // Of the fitting octree; the tiles are its cubes.
  double data_margin = 0;        // A tile reads the points within this of its cube.
  double extraction_margin = 0;  // Its function must be exact this far around its cube.
  std::vector<uint64_t> tiles;   // The cubes near the data (grid keys), in welding order.
  // What planning measured and cost.
  int64_t points = 0;
  int64_t scratch_bytes = 0;
  double measure_seconds = 0, scan_seconds = 0, spacing_seconds = 0;
};

// The format of plans and parts, as bytes and as what a part holds (4: tiles refine acute creases
// and thin walls as untiled): servers of other formats cannot read each other's
// (their child jobs are of another format: jobs::TileChildFormat). Raised with every change to either.
inline constexpr int kTileFormat = 4;

// The plan as bytes ("LQTP"), for servers of the same build. Errors: kInvalidArgument.
std::string EncodeTilePlan(const TilePlan& plan);
absl::StatusOr<TilePlan> DecodeTilePlan(std::string_view bytes);
// Whether two encoded plans cut the same cloud into the same tiles with the same parameters (all
// but the timings planning measured), so that the parts made for one are the other's.
bool SameTilePlan(std::string_view a, std::string_view b);

// The cloud's plan and each tile's points, kept in files under a directory of its own below
// `scratch_parent` (the system's temporary directory when empty), removed with this object.
class PlannedCloud {
 public:
  // Reads `source` three times (bounds; a histogram that sets the tiles; the points bucketed with
  // their margins) and measures the frame over the tiles (mean nearest-neighbour distance
  // exactly, noise as the median of the tiles'). Errors: kInvalidArgument (no normals, non-finite
  // points, fewer than 4, bad parameters), kUnavailable (scratch files), kCancelled.
  static absl::StatusOr<std::unique_ptr<PlannedCloud>> Plan(const PointSource& source, const PuParams& fit,
                                                            const PuExtractParams& extract, const PuTileParams& tiles,
                                                            core::JobContext& ctx,
                                                            const std::string& scratch_parent = "");
  ~PlannedCloud();
  const TilePlan& plan() const { return plan_; }
  // The points RunTile needs for tile `index` of the plan. Errors: kOutOfRange, kUnavailable.
  absl::StatusOr<core::PointCloud> TilePoints(size_t index) const;

 private:
  struct Files;
  PlannedCloud(TilePlan plan, std::unique_ptr<Files> files);
  TilePlan plan_;
  std::unique_ptr<Files> files_;
};

// Tile `index` of `plan` from its points, extracted with the plan's parameters: its part of the surface (with the
// lattice edges of its border vertices, so that TileJoiner can weld it) and its statistics, as bytes ("LQT1"). A tile
// the surface does not cross gives a part without faces. The same inputs give the same bytes on
// any server of the same build. Errors: kInvalidArgument, as BuildPu and Extract, kCancelled.
absl::StatusOr<std::string> RunTile(const TilePlan& plan, size_t index, core::PointCloud points, core::JobContext& ctx);

// A tile's oriented points as bytes, to hand to another server. Errors: kInvalidArgument.
std::string EncodeTilePoints(const core::PointCloud& points);
absl::StatusOr<core::PointCloud> DecodeTilePoints(std::string_view bytes);

// Welds the parts RunTile made, given in the plan's order, handing each to `sink` with its
// vertices numbered on from the parts before it (border vertices shared by lattice edge).
class TileJoiner {
 public:
  TileJoiner(const TilePlan& plan, SurfaceSink& sink);
  ~TileJoiner();
  // Errors: kInvalidArgument (unreadable bytes, or not the next tile), the sink's.
  absl::Status Add(std::string_view tile);
  size_t next_tile() const;  // The plan index Add expects.
  // The statistics of the whole build. Errors: kFailedPrecondition (tiles missing, or no faces).
  absl::StatusOr<TiledStats> Finish();

 private:
  struct State;
  std::unique_ptr<State> state_;
};

// The PU surface of `source`, tile by tile, with memory bounded by the tile size: the cloud is
// read three times (bounds; a histogram that sets the tiles; the points bucketed into one file
// per tile with its margin, under `scratch_parent`), the frame is measured over the tiles (mean
// nearest-neighbour distance exactly, noise as the median of the tiles'), then each tile is fitted
// and extracted and its part of the surface handed to `sink`. Errors: kInvalidArgument (no
// normals, non-finite points, fewer than 4), as BuildPu and Extract, kCancelled.
absl::StatusOr<TiledStats> ReconstructTiled(const PointSource& source, const PuParams& fit,
                                            const PuExtractParams& extract, const PuTileParams& tiles,
                                            SurfaceSink& sink, core::JobContext& ctx,
                                            const std::string& scratch_parent = "");

// Removes the scratch directories a tiled build made under `parent` for a process that is no
// longer alive (a crashed server's point files, gigabytes on a large cloud); returns how many.
// Errors: kUnavailable (`parent` cannot be read).
absl::StatusOr<int> SweepAbandonedScratch(const std::string& parent);

}  // namespace lsqsurf::pu
