#include "worker/jobs/tile_exchange.h"

#include <spdlog/spdlog.h>

#include <algorithm>

#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::jobs {
namespace {

constexpr char kPlanBlob[] = "tile-plan";

std::string TileBlob(std::string_view kind, int64_t tile) { return core::StrCat("tile-", kind, "-", tile); }

// A failed tile's status as its child job's error: "status N: message", the code kept for the
// build's server (a child's error is never shown to a user).
constexpr std::string_view kCodePrefix = "status ";
absl::Status TileError(const absl::Status& status) {
  return absl::Status(status.code(),
                      core::StrCat(kCodePrefix, static_cast<int>(status.code()), ": ", status.message()));
}

}  // namespace

absl::Status DecodeTileError(int64_t tile, std::string_view stored) {
  int code = static_cast<int>(absl::StatusCode::kInternal);
  if (stored.starts_with(kCodePrefix)) {
    const size_t colon = stored.find(": ");
    if (colon != std::string_view::npos) {
      const int read = std::atoi(std::string(stored.substr(kCodePrefix.size(), colon - kCodePrefix.size())).c_str());
      if (read > 0 && read <= static_cast<int>(absl::StatusCode::kUnauthenticated)) code = read;
      stored.remove_prefix(colon + 2);
    }
  }
  return absl::Status(static_cast<absl::StatusCode>(code), core::StrCat("tile ", tile, ": ", stored));
}

absl::Status RunTileJob(BlobStore& blobs, const JobRecord& child, core::JobContext& ctx,
                        const std::function<bool()>& parent_running) {
  const std::string& build = child.parent;
  const int64_t tile = child.child_index;
  // A tile that throws fails its build with the code it would have as a job, never the server.
  auto part = core::CatchEngineErrors("tile", [&]() -> absl::StatusOr<std::string> {
    auto plan_bytes = blobs.Read(build, kPlanBlob);
    if (!plan_bytes.ok()) return plan_bytes.status();
    auto point_bytes = blobs.Read(build, TileBlob("points", tile));
    if (!point_bytes.ok()) return point_bytes.status();
    auto plan = pu::DecodeTilePlan(*plan_bytes);
    if (!plan.ok()) return plan.status();
    auto points = pu::DecodeTilePoints(*point_bytes);
    if (!points.ok()) return points.status();
    point_bytes->clear();
    return pu::RunTile(*plan, static_cast<size_t>(tile), *std::move(points), ctx);
  });
  if (absl::IsCancelled(part.status())) return part.status();
  if (absl::IsNotFound(part.status()) && parent_running()) {
    return TileError(absl::FailedPreconditionError(core::StrCat(
        "tile ", tile, " of job ", build, " cannot be read from the blob store of the server that ran it (",
        part.status().message(), "): it is not the store the other servers share")));
  }
  if (!part.ok()) return TileError(part.status());
  // Only for a build that still runs: a part stored after its job was deleted would stay behind.
  if (!parent_running()) return absl::CancelledError(core::StrCat("job ", build, " ended"));
  return blobs.Put(build, TileBlob("part", tile), *part);
}

absl::Status StoreTileExchange::QueueChild(int64_t tile) {
  JobRecord child;
  child.id = core::StrCat(parent_.id, "-a", parent_.attempts, "-t", tile);
  child.spec.method = kTileMethod;
  child.state = JobState::kQueued;
  child.created_ms = parent_.created_ms;  // Queued with its build, before the jobs after it.
  child.updated_ms = child.created_ms;
  child.owner = parent_.owner;
  child.quota_bytes = parent_.quota_bytes;
  child.spec_format = jobs_.child_format;
  child.parent = parent_.id;
  child.child_index = tile;
  LSQSURF_RETURN_IF_ERROR(store_.Insert(child));
  child_of_tile_[static_cast<size_t>(tile)] = child.id;
  return absl::OkStatus();
}

absl::Status StoreTileExchange::Publish(std::string_view plan, int64_t tiles,
                                        const std::function<absl::StatusOr<std::string>(int64_t)>& points) {
  tiles_ = tiles;
  child_of_tile_.assign(static_cast<size_t>(tiles), "");
  reused_tiles_.clear();
  // An earlier attempt of the build (its server stopped) under the same plan: its children's parts
  // are this plan's, to the byte, and those still queued or running go on as this attempt's.
  auto earlier = blobs_.Read(parent_.id, kPlanBlob);
  const bool same_plan = earlier.ok() && pu::SameTilePlan(*earlier, plan);
  for (const JobRecord& child : jobs_.children(parent_.id)) {
    const int64_t t = child.child_index;
    const bool usable = same_plan && t >= 0 && t < tiles && child_of_tile_[static_cast<size_t>(t)].empty() &&
                        child.spec_format == jobs_.child_format && child.state != JobState::kCancelled;
    if (!usable) {
      if (!IsTerminal(child.state)) (void)store_.Cancel(child.id, "its build started over under another plan");
      continue;
    }
    if (child.state == JobState::kSucceeded && !blobs_.Exists(parent_.id, TileBlob("part", t))) continue;
    // A tile whose servers stopped on each of its attempts fails the build again: the same plan
    // gives it the same points.
    if (child.state == JobState::kFailed) return DecodeTileError(t, child.error);
    child_of_tile_[static_cast<size_t>(t)] = child.id;
    if (child.state == JobState::kSucceeded) reused_tiles_.insert(t);
  }
  reused_ = static_cast<int64_t>(reused_tiles_.size());
  LSQSURF_RETURN_IF_ERROR(blobs_.Put(parent_.id, kPlanBlob, plan));
  for (int64_t t = 0; t < tiles; ++t) {
    if (!child_of_tile_[static_cast<size_t>(t)].empty()) continue;
    auto bytes = points(t);
    if (!bytes.ok()) return bytes.status();
    LSQSURF_RETURN_IF_ERROR(blobs_.Put(parent_.id, TileBlob("points", t), *bytes));
    LSQSURF_RETURN_IF_ERROR(blobs_.Remove(parent_.id, TileBlob("part", t)));  // An earlier attempt's.
    LSQSURF_RETURN_IF_ERROR(QueueChild(t));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> StoreTileExchange::Part(int64_t tile, core::JobContext& ctx) {
  const std::string& id = child_of_tile_.at(static_cast<size_t>(tile));
  for (;;) {
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
    auto child = jobs_.get(id);
    if (!child.ok()) return child.status();
    if (child->state == JobState::kSucceeded) {
      auto part = blobs_.Read(parent_.id, TileBlob("part", tile));
      if (!part.ok()) return part.status();
      if (!reused_tiles_.contains(tile)) servers_.insert(child->runner);
      // The part is welded now: its points are not needed any more. The part stays until the
      // build ends, for a later attempt should this server stop.
      (void)blobs_.Remove(parent_.id, TileBlob("points", tile));
      return part;
    }
    if (child->state == JobState::kFailed) return DecodeTileError(tile, child->error);
    if (child->state == JobState::kCancelled) {
      return absl::AbortedError(core::StrCat("tile ", tile, " was cancelled: ", child->error));
    }
    // While a child of this build waits in the queue, this server makes it; otherwise it waits
    // for the next change, which the store's feed brings.
    if (jobs_.any_queued(parent_.id)) {
      auto ran = jobs_.run_one(parent_.id);
      if (!ran.ok()) return ran.status();
      if (*ran) continue;
    }
    jobs_.wait(jobs_.wait_limit);
  }
}

void StoreTileExchange::Clear() {
  for (const JobRecord& child : jobs_.children(parent_.id)) {
    // A child still running elsewhere stops at its runner's next renewal and goes with the build.
    if (!IsTerminal(child.state)) {
      auto cancelled = store_.Cancel(child.id, "its build ended");
      if (!cancelled.ok() || !IsTerminal(cancelled->state)) continue;
    }
    if (absl::Status s = store_.Remove(child.id); !s.ok() && !absl::IsNotFound(s)) {
      spdlog::warn("[job {}] cannot remove its tile job {}: {}", parent_.id, child.id, s.ToString());
    }
  }
  (void)blobs_.Remove(parent_.id, kPlanBlob);
  for (int64_t t = 0; t < tiles_; ++t) {
    for (const char* kind : {"points", "part"}) (void)blobs_.Remove(parent_.id, TileBlob(kind, t));
  }
}

absl::StatusOr<pu::TiledStats> ReconstructTiledShared(const pu::PointSource& source, const pu::PuParams& fit,
                                                      const pu::PuExtractParams& extract, const pu::PuTileParams& tiles,
                                                      pu::SurfaceSink& sink, core::JobContext& ctx,
                                                      const TiledRun& run) {
  TileExchange& exchange = *run.exchange;
  core::SubContext measure_ctx(ctx, "measuring the cloud", 0.0, 0.15);
  auto planned = pu::PlannedCloud::Plan(source, fit, extract, tiles, measure_ctx, run.scratch_dir);
  if (!planned.ok()) return planned.status();
  const pu::TilePlan plan = (*planned)->plan();
  struct Clear {
    TileExchange& exchange;
    ~Clear() { exchange.Clear(); }
  } clear{exchange};
  const auto count = static_cast<int64_t>(plan.tiles.size());
  core::SubContext publish_ctx(ctx, "sharing the tiles", 0.15, 0.2);
  LSQSURF_RETURN_IF_ERROR(
      exchange.Publish(pu::EncodeTilePlan(plan), count, [&](int64_t t) -> absl::StatusOr<std::string> {
        publish_ctx.ReportProgress("sharing the tiles", static_cast<double>(t) / static_cast<double>(count));
        LSQSURF_RETURN_IF_ERROR(publish_ctx.CheckCancelled());
        auto points = (*planned)->TilePoints(static_cast<size_t>(t));
        if (!points.ok()) return points.status();
        return pu::EncodeTilePoints(*points);
      }));
  planned->reset();  // The points are in the blob store now; their files go.
  pu::TileJoiner joiner(plan, sink);
  core::SubContext tiles_ctx(ctx, "fitting and extracting tiles", 0.2, 1.0);
  for (int64_t t = 0; t < count; ++t) {
    core::SubContext tile_ctx(tiles_ctx, core::StrCat("tile ", t + 1, " of ", count),
                              static_cast<double>(t) / static_cast<double>(count),
                              static_cast<double>(t + 1) / static_cast<double>(count));
    auto part = exchange.Part(t, tile_ctx);
    if (!part.ok()) return part.status();
    LSQSURF_RETURN_IF_ERROR(joiner.Add(*part));
  }
  return joiner.Finish();
}

}  // namespace lsqsurf::jobs
