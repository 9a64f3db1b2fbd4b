#include "worker/jobs/tile_exchange.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <exception>
#include <new>
#include <thread>

#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::jobs {
namespace {

constexpr char kPlanBlob[] = "tile-plan";
// How long the job's server waits between looks at the store when no tile is left to claim and
// the next part is not made yet: short beside a tile's seconds.
constexpr std::chrono::milliseconds kPartPoll(200);

std::string TileBlob(std::string_view kind, int64_t tile) { return core::StrCat("tile-", kind, "-", tile); }

// A failed tile's status as the text of its error blob: the code's number, a newline, the message.
std::string EncodeError(const absl::Status& status) {
  return core::StrCat(static_cast<int>(status.code()), "\n", status.message());
}
absl::Status DecodeError(int64_t tile, std::string_view text) {
  const size_t newline = text.find('\n');
  int code = static_cast<int>(absl::StatusCode::kInternal);
  if (newline != std::string_view::npos) {
    const int read = std::atoi(std::string(text.substr(0, newline)).c_str());
    if (read > 0 && read <= static_cast<int>(absl::StatusCode::kUnauthenticated)) code = read;
    text.remove_prefix(newline + 1);
  }
  return absl::Status(static_cast<absl::StatusCode>(code), core::StrCat("tile ", tile, ": ", text));
}

// A tile claimed more often than `max_attempts` stopped the server making it every time (out of
// memory, a crash): it fails its job with that reason instead of taking down one server after
// another. Its error blob is stored as a failed tile's, and the tile is done.
absl::Status GiveUpTile(JobStore& store, BlobStore& blobs, const std::string& runner, const TileTask& task) {
  const absl::Status reason = absl::InternalError(
      core::StrCat("the server making it stopped on each of its ", task.attempts - 1,
                   " attempts (out of memory or a crash); lower tile_points or give the servers more memory"));
  spdlog::error("[job {}] tile {}: {}", task.job_id, task.tile, reason.message());
  LSQSURF_RETURN_IF_ERROR(blobs.Put(task.job_id, TileBlob("error", task.tile), EncodeError(reason)));
  return store.FinishTile(task, runner);
}

}  // namespace

absl::StatusOr<TileBlobBytes> RunSharedTile(BlobStore& blobs, const std::string& job_id, int64_t tile,
                                            core::JobContext& ctx) {
  auto plan_bytes = blobs.Read(job_id, kPlanBlob);
  if (!plan_bytes.ok()) return plan_bytes.status();
  auto point_bytes = blobs.Read(job_id, TileBlob("points", tile));
  if (!point_bytes.ok()) return point_bytes.status();
  auto part = [&]() -> absl::StatusOr<std::string> {
    auto plan = pu::DecodeTilePlan(*plan_bytes);
    if (!plan.ok()) return plan.status();
    auto points = pu::DecodeTilePoints(*point_bytes);
    if (!points.ok()) return points.status();
    point_bytes->clear();
    // A tile that throws fails its job, as a job's run does (JobService::RunKind), and never the
    // server: every replica would claim it in turn.
    try {
      return pu::RunTile(*plan, static_cast<size_t>(tile), *std::move(points), ctx);
    } catch (const std::bad_alloc&) {
      return absl::ResourceExhaustedError("the tile ran out of memory");
    } catch (const std::exception& e) {
      return absl::InternalError(core::StrCat("engine error: ", e.what()));
    }
  }();
  if (part.ok()) return TileBlobBytes{TileBlob("part", tile), *std::move(part)};
  if (absl::IsCancelled(part.status())) return part.status();
  return TileBlobBytes{TileBlob("error", tile), EncodeError(part.status())};
}

absl::StatusOr<bool> RunClaimedTile(JobStore& store, BlobStore& blobs, const std::string& runner,
                                    const TileClaimOptions& options, core::JobContext& ctx, const std::string& job_id) {
  auto claimed = store.ClaimTile(runner, options.lease, options.build, job_id);
  if (!claimed.ok()) return claimed.status();
  if (!claimed->has_value()) return false;
  const TileTask& task = **claimed;
  if (options.max_attempts > 0 && task.attempts > options.max_attempts) {
    if (absl::Status s = GiveUpTile(store, blobs, runner, task); !s.ok()) {
      spdlog::warn("[job {}] tile {}: {}", task.job_id, task.tile, s.ToString());
    }
    return true;
  }
  const StoreTileExchange::HoldFn& hold = options.hold;
  hold(task, true);
  const auto start = std::chrono::steady_clock::now();
  absl::Status ran = absl::OkStatus();
  auto made = RunSharedTile(blobs, task.job_id, task.tile, ctx);
  // Not this tile's fault, so not one of its attempts: this server stops, or cannot see the blobs
  // the job's server published (its blob store is not the one the others share) while the job runs.
  const bool stopping = absl::IsCancelled(made.status()) && ctx.IsCancelled();
  const bool unreadable = absl::IsNotFound(made.status()) && [&] {
    auto job = store.Get(task.job_id);
    return job.ok() && job->state == JobState::kRunning;
  }();
  if (stopping || unreadable) {
    hold(task, false);
    if (absl::Status s = store.ReleaseTile(task, runner); !s.ok() && !absl::IsAborted(s)) return s;
    if (stopping) return made.status();
    return absl::FailedPreconditionError(
        core::StrCat("tile ", task.tile, " of job ", task.job_id, " cannot be read from this server's blob store (",
                     made.status().message(), "): it is not the store the other servers share"));
  }
  if (!made.ok()) {
    ran = made.status();
  } else {
    // Only for a job that still runs: a part stored after its job was deleted would stay behind.
    auto job = store.Get(task.job_id);
    ran = !job.ok()                          ? job.status()
          : job->state != JobState::kRunning ? absl::CancelledError(core::StrCat("job ", task.job_id, " ended"))
                                             : blobs.Put(task.job_id, made->name, made->bytes);
  }
  if (ran.ok()) {
    spdlog::info("[job {}] tile {} made here in {:.2f} s (attempt {})", task.job_id, task.tile,
                 core::SecondsSince(start), task.attempts);
  }
  // A tile that was not made goes back to the others when its lease lapses; one that was is done.
  const absl::Status finished = ran.ok() ? store.FinishTile(task, runner) : ran;
  hold(task, false);
  if (!finished.ok() && !absl::IsCancelled(finished)) {
    spdlog::warn("[job {}] tile {}: {}", task.job_id, task.tile, finished.ToString());
  }
  if (absl::IsCancelled(ran) && ctx.IsCancelled()) return ran;
  return true;
}

absl::Status StoreTileExchange::Publish(std::string_view plan, int64_t tiles,
                                        const std::function<absl::StatusOr<std::string>(int64_t)>& points) {
  tiles_ = tiles;
  done_.clear();
  // An earlier attempt of the job (its server stopped) under the same plan: the parts it left
  // are this plan's, to the byte.
  std::vector<int64_t> kept;
  if (auto earlier = blobs_.Read(job_id_, kPlanBlob); earlier.ok() && pu::SameTilePlan(*earlier, plan)) {
    for (int64_t t = 0; t < tiles; ++t) {
      if (blobs_.Exists(job_id_, TileBlob("part", t))) kept.push_back(t);
    }
  }
  reused_ = static_cast<int64_t>(kept.size());
  LSQSURF_RETURN_IF_ERROR(blobs_.Put(job_id_, kPlanBlob, plan));
  for (int64_t t = 0, next_kept = 0; t < tiles; ++t) {
    if (next_kept < reused_ && kept[static_cast<size_t>(next_kept)] == t) {
      ++next_kept;
      continue;
    }
    auto bytes = points(t);
    if (!bytes.ok()) return bytes.status();
    LSQSURF_RETURN_IF_ERROR(blobs_.Put(job_id_, TileBlob("points", t), *bytes));
    // What an earlier attempt of the job left.
    LSQSURF_RETURN_IF_ERROR(blobs_.Remove(job_id_, TileBlob("part", t)));
    LSQSURF_RETURN_IF_ERROR(blobs_.Remove(job_id_, TileBlob("error", t)));
  }
  return store_.AddTiles(job_id_, tiles, claims_.build, kept);
}

absl::StatusOr<std::string> StoreTileExchange::Part(int64_t tile, core::JobContext& ctx) {
  for (;;) {
    LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
    if (!done_.contains(tile)) {
      auto done = store_.DoneTiles(job_id_);
      if (!done.ok()) return done.status();
      for (auto& [t, runner] : *done) done_[t] = std::move(runner);
    }
    if (auto it = done_.find(tile); it != done_.end()) {
      // A failed tile left its reason instead of a part.
      auto text = blobs_.Read(job_id_, TileBlob("error", tile));
      if (text.ok()) return DecodeError(tile, *text);
      if (!absl::IsNotFound(text.status())) return text.status();
      auto part = blobs_.Read(job_id_, TileBlob("part", tile));
      if (!part.ok()) return part.status();
      if (!it->second.empty()) servers_.insert(it->second);  // Not a reused part.
      // The part is welded now: its points are not needed any more. The part stays until the
      // build ends, for a later attempt should this server stop.
      (void)blobs_.Remove(job_id_, TileBlob("points", tile));
      return part;
    }
    auto ran = RunClaimedTile(store_, blobs_, runner_, claims_, ctx, job_id_);
    if (!ran.ok()) return ran.status();
    if (!*ran) std::this_thread::sleep_for(kPartPoll);  // Every tile left is with another server.
  }
}

void StoreTileExchange::Clear() {
  if (absl::Status s = store_.RemoveTiles(job_id_); !s.ok()) {
    spdlog::warn("[job {}] cannot drop its tiles: {}", job_id_, s.ToString());
  }
  (void)blobs_.Remove(job_id_, kPlanBlob);
  for (int64_t t = 0; t < tiles_; ++t) {
    for (const char* kind : {"points", "part", "error"}) (void)blobs_.Remove(job_id_, TileBlob(kind, t));
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
