// worker/jobs/tile_exchange.h — one tiled PU build spread over the servers that share a store.
//
// The server running the job plans it (pu::PlannedCloud), puts the plan and each tile's points
// in the blob store and queues the tiles in the job store. Every server with an idle worker
// claims tiles of running jobs (JobStore::ClaimTile), runs them from those blobs alone
// (RunSharedTile) and stores their parts; a tile whose server died is claimed again when its
// lease lapses. The job's server runs tiles too while it waits, and welds the parts in tile
// order as they come (pu::TileJoiner), so the surface is the one a single server makes.
//
// Blobs of the job while it runs: tile-plan, tile-points-N, tile-part-N (or tile-error-N, the
// reason a tile could not be made); all are removed when the build ends. A build resumed after its
// server stopped uses the parts the earlier attempt made under the same plan (Reused). A tile
// whose servers stopped while making it more than TileClaimOptions::max_attempts times fails its
// job; tiles are claimed only by servers of the same pu::kTileFormat.
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

// What a tile leaves in the blob store: its part (tile-part-N), or where it failed the reason, for
// the job's server to report (tile-error-N).
struct TileBlobBytes {
  std::string name;
  std::string bytes;
};

// Makes tile `tile` of job `job_id` from the blobs its server published. Errors: kCancelled,
// kNotFound (the build is gone), kUnavailable.
absl::StatusOr<TileBlobBytes> RunSharedTile(BlobStore& blobs, const std::string& job_id, int64_t tile,
                                            core::JobContext& ctx);

// How a server claims and runs tiles.
struct TileClaimOptions {
  // `hold(task, true)` before this server runs a tile, `hold(task, false)` after: the tiles whose
  // leases its renewal extends.
  using HoldFn = std::function<void(const TileTask&, bool)>;
  std::chrono::milliseconds lease{0};
  HoldFn hold;
  // A tile claimed more often than this (its servers stopped while making it: out of memory, a
  // crash) fails its job, naming the tile; 0 = no limit. A server's graceful stop counts too.
  int max_attempts = 0;
  // The tile format this server publishes its tiles as and claims others' in: its build's
  // (pu::kTileFormat), or another one to test a mixed rolling update.
  int build = pu::kTileFormat;
};

// The exchange over a job store and a blob store that servers share.
class StoreTileExchange final : public TileExchange {
 public:
  using HoldFn = TileClaimOptions::HoldFn;
  StoreTileExchange(JobStore& store, BlobStore& blobs, std::string job_id, std::string runner, TileClaimOptions claims)
      : store_(store),
        blobs_(blobs),
        job_id_(std::move(job_id)),
        runner_(std::move(runner)),
        claims_(std::move(claims)) {}

  absl::Status Publish(std::string_view plan, int64_t tiles,
                       const std::function<absl::StatusOr<std::string>(int64_t)>& points) override;
  absl::StatusOr<std::string> Part(int64_t tile, core::JobContext& ctx) override;
  int Servers() const override { return static_cast<int>(servers_.size()); }
  int64_t Reused() const override { return reused_; }
  void Clear() override;

 private:
  JobStore& store_;
  BlobStore& blobs_;
  std::string job_id_, runner_;
  TileClaimOptions claims_;
  int64_t tiles_ = 0, reused_ = 0;
  std::map<int64_t, std::string> done_;  // Tile → the runner that finished it.
  std::set<std::string> servers_;
};

// Claims one tile of any running job (of `job_id` where given) for `runner`, runs it
// (RunSharedTile) and stores what it left if the job still runs, holding the tile through
// `options.hold` meanwhile; a tile past `options.max_attempts` is failed instead. False when there
// was none. A tile not made because this server stops or cannot read its blobs is given back
// (JobStore::ReleaseTile). Errors: kCancelled (`ctx`), kFailedPrecondition (the tile's blobs are
// not in `blobs` while its job runs: this server's blob store is not the shared one), kUnavailable.
absl::StatusOr<bool> RunClaimedTile(JobStore& store, BlobStore& blobs, const std::string& runner,
                                    const TileClaimOptions& options, core::JobContext& ctx,
                                    const std::string& job_id = "");

}  // namespace lsqsurf::jobs
