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

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"
#include "worker/pu/pu.h"

namespace lsqsurf::pu {

struct PuTileParams {
  // A cloud of more points than this is reconstructed in tiles, cubes of the fitting octree small
  // enough to hold at most this many points each (their margins add about a third on a surface).
  // Memory per tile follows it (about 2 KB a point for build and extraction).
  int64_t tile_points = 4'000'000;
  // The largest support radius of a tiled build, in mean point spacings (8..512). Larger cells
  // are split without a fit and no fitting ball grows past it; margins are 2 of these plus four
  // coarse extraction cells.
  double support_cap = 64;
};

const core::ParamTable<PuTileParams>& PuTileParamTable();

// What a tiled build fixes for every tile (MeasureFrame).
struct PuFrame {
  core::Vec3d origin = core::Vec3d::Zero();  // The fitting octree's root cube.
  double root_edge = 0;
  double diagonal = 0;        // Of the whole cloud's bounding box.
  double mean_spacing = 0;    // Mean nearest-neighbour distance.
  double noise_estimate = 0;  // σ, share of the diagonal.
  PuParams params;            // After the noise adjustment.
  double max_support = 0;     // Model units.
};

// The frame of `cloud` for `params`, with max_support = support_cap mean spacings (at least the
// support of the deepest cells). Errors: kInvalidArgument (as BuildPu), kCancelled.
absl::StatusOr<PuFrame> MeasureFrame(const core::PointCloud& cloud, const PuParams& params, double support_cap,
                                     core::JobContext& ctx);

// F of `cloud` in `frame`: with `region`, exact over it (equal to the build over the whole cloud)
// when `cloud` holds every point within 2 × max_support of it; cells whose supports cannot reach
// it are not grown. Errors: as BuildPu.
absl::StatusOr<std::unique_ptr<PuFunction>> BuildPuInFrame(const core::PointCloud& cloud, const PuFrame& frame,
                                                           const core::Box3* region, core::JobContext& ctx);

struct TiledStats {
  int64_t tiles = 0;           // Tiles that made faces.
  int64_t tiles_examined = 0;  // Tiles near the data.
  int tile_level = 0;          // Of the fitting octree.
  int64_t largest_tile = 0;    // Points one tile read, its margin included.
  int64_t seam_vertices = 0;   // Vertices two or more tiles shared.
  double margin = 0;           // Model units.
  PuStats fit;                 // Summed over the tiles (fits of margins counted once per tile).
};

// The surface of `cloud` in `frame`, tile by tile (cloud in memory: the tiles' functions and
// trees are what stays bounded). Every tile's part is passed to `on_tile` (when set) as soon as it
// is done, its vertices already numbered as in the final mesh (so a sink can write them out).
// Errors: as BuildPu and Extract.
struct TilePart {
  int64_t index = 0;
  const core::TriangleMesh* mesh = nullptr;  // The merged mesh so far.
  size_t first_face = 0;                     // This tile's faces: [first_face, mesh->faces.size()).
};
absl::StatusOr<extract::IsosurfaceResult> ExtractTiled(const core::PointCloud& cloud, const PuFrame& frame,
                                                       const PuExtractParams& params, const PuTileParams& tiles,
                                                       core::JobContext& ctx, TiledStats* stats = nullptr,
                                                       const std::function<void(const TilePart&)>& on_tile = {});

}  // namespace lsqsurf::pu
