// worker/jobs/tile_exchange.h — one tiled PU build spread over the servers that share a store.
//
// A tile is a child job of the build's job (JobRecord::parent), in the one job queue. The
// server running the build plans it (pu::PlannedCloud), puts the plan and each tile's points in
// the blob store under the build's job, and queues one child job per tile. Any server's worker
// claims children of running builds before new jobs (ClaimScope), makes the tile's part from
// those blobs (RunTileJob) and stores it under the build's job; leases, takeover, attempt limits,
// cancellation and metrics are the job path's. The build's server runs its own children while it
// waits and otherwise sleeps on the job table's changes (the store's change feed); it welds the
// parts in tile order as they come (pu::TileJoiner), so the surface is the one a single server
// makes.
//
// Blobs of the build's job while it runs: tile-plan, tile-points-N, tile-part-N; all are removed,
// with the children, when the build ends. A build resumed after its server stopped takes over the
// children an earlier attempt queued under the same plan, finished ones included (Reused); a tile
// whose child failed (its servers stopped on each of max_attempts runs) fails the build, naming it.
// Children are of the format TileChildFormat(pu::kTileFormat): only servers of that format claim them.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <set>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/job_context.h"
#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::jobs {

// Where a build's tiles run. The job's run uses it; JobService makes one per run on a shared store.
class TileExchange {
 public:
  virtual ~TileExchange() = default;
  // Makes `tiles` tiles available to every server: the plan, and each tile's points from `points`.
  // Errors: kUnavailable, kResourceExhausted (storage), those of `points`.
  virtual absl::Status Publish(std::string_view plan, int64_t tiles,
                               const std::function<absl::StatusOr<std::string>(int64_t)>& points) = 0;
  // Tile `tile`'s part, once a server has made it; meanwhile this server runs tiles of the build
  // itself. Errors: kCancelled, kUnavailable, the error that tile met.
  virtual absl::StatusOr<std::string> Part(int64_t tile, core::JobContext& ctx) = 0;
  // The servers that made the parts Part returned: their runner names, one per process (servers
  // of one name, as replicas on one host without --name are, count apart).
  virtual int Servers() const = 0;
  // The tiles whose parts an earlier attempt of the job made under the same plan, used again.
  virtual int64_t Reused() const = 0;
  // Drops the tiles and their blobs.
  virtual void Clear() = 0;
};

// Where a tiled run keeps its point files ("": the system's temporary directory) and, where
// given, the exchange that spreads its tiles over the servers.
struct TiledRun {
  std::string scratch_dir;
  TileExchange* exchange = nullptr;
};

// The tiled PU surface of `source` with its tiles run through `exchange`: the surface
// pu::ReconstructTiled makes, handed to `sink` in the same parts. Errors: as ReconstructTiled,
// and the exchange's.
absl::StatusOr<pu::TiledStats> ReconstructTiledShared(const pu::PointSource& source, const pu::PuParams& fit,
                                                      const pu::PuExtractParams& extract, const pu::PuTileParams& tiles,
                                                      pu::SurfaceSink& sink, core::JobContext& ctx,
                                                      const TiledRun& run);

// The spec method of a tile's child job, never one of the registry's.
inline constexpr char kTileMethod[] = "tile";
// The spec format of the child jobs of tiles of format `tile_format` (pu::kTileFormat).
inline int TileChildFormat(int tile_format) { return kChildFormatBase + tile_format; }

// Makes the part of the tile child job `child` from the blobs its build's server published and
// stores it under the build's job, if `parent_running` still says so when it is made. Errors:
// kCancelled (`ctx`, or the build ended), kFailedPrecondition (the tile's blobs are not in
// `blobs` while the build runs: this server's blob store is not the shared one), and the
// tile's own, each with its code in the message for the build (DecodeTileError).
absl::Status RunTileJob(BlobStore& blobs, const JobRecord& child, core::JobContext& ctx,
                        const std::function<bool()>& parent_running);

// A tile child's stored error, as the build's server reports it: "tile N: ..." with the code
// RunTileJob kept.
absl::Status DecodeTileError(int64_t tile, std::string_view stored);

// How a build's server follows the child jobs of its tiles and helps with them: the job
// runner's table and workers.
struct TileJobs {
  // The newest record of a job this server knows. Errors: kNotFound.
  std::function<absl::StatusOr<JobRecord>(const std::string& id)> get;
  // The child jobs of `parent` this server knows of, in any state.
  std::function<std::vector<JobRecord>(const std::string& parent)> children;
  // Whether one of them is queued (asked with every look, so without copying their records).
  std::function<bool(const std::string& parent)> any_queued;
  // Claims one queued child of `parent` and runs it here to its end; false when none was queued.
  // Errors: kUnavailable.
  std::function<absl::StatusOr<bool>(const std::string& parent)> run_one;
  // Returns when any job changed (here or on another server), or after `timeout`.
  std::function<void(std::chrono::milliseconds timeout)> wait;
  std::chrono::milliseconds wait_limit{30'000};  // The longest wait between two looks.
  int child_format = TileChildFormat(pu::kTileFormat);
};

// The exchange over child jobs in a job store and a blob store that servers share.
class StoreTileExchange final : public TileExchange {
 public:
  // `parent` is the build's job as its run holds it.
  StoreTileExchange(JobStore& store, BlobStore& blobs, JobRecord parent, TileJobs jobs)
      : store_(store), blobs_(blobs), parent_(std::move(parent)), jobs_(std::move(jobs)) {}

  absl::Status Publish(std::string_view plan, int64_t tiles,
                       const std::function<absl::StatusOr<std::string>(int64_t)>& points) override;
  absl::StatusOr<std::string> Part(int64_t tile, core::JobContext& ctx) override;
  int Servers() const override { return static_cast<int>(servers_.size()); }
  int64_t Reused() const override { return reused_; }
  void Clear() override;

 private:
  // Queues a child job for tile `tile` of this attempt.
  absl::Status QueueChild(int64_t tile);

  JobStore& store_;
  BlobStore& blobs_;
  const JobRecord parent_;
  TileJobs jobs_;
  int64_t tiles_ = 0, reused_ = 0;
  std::vector<std::string> child_of_tile_;  // The child job making each tile.
  std::set<int64_t> reused_tiles_;
  std::set<std::string> servers_;
};

}  // namespace lsqsurf::jobs
