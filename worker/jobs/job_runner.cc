#include "worker/jobs/job_runner.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/jobs/job_service_internal.h"
#include "worker/jobs/tile_exchange.h"

namespace lsqsurf::jobs {
namespace {

// A failed job's stored reason, at most.
constexpr size_t kMaxJobErrorBytes = 4096;

}  // namespace

// Writes a job's artifacts into the blob store, recording their names in order.
// Each write is first admitted with what all the job's artifacts would then take (quotas).
class BlobSink final : public ArtifactSink {
 public:
  using Admit = std::function<absl::Status(int64_t artifact_bytes)>;
  using Publish = std::function<void(const std::string& name)>;
  // `publish` lists an artifact in the job's results while it runs (MeshPartArtifact).
  BlobSink(BlobStore& blobs, std::string job_id, Admit admit, Publish publish)
      : blobs_(blobs), job_id_(std::move(job_id)), admit_(std::move(admit)), publish_(std::move(publish)) {}
  absl::Status Write(std::string_view name, std::string_view bytes) override {
    {
      std::lock_guard lock(mutex_);
      int64_t after = static_cast<int64_t>(bytes.size());
      for (const auto& [kept, size] : sizes_) after += kept == name ? 0 : size;
      LSQSURF_RETURN_IF_ERROR(admit_(after));
    }
    LSQSURF_RETURN_IF_ERROR(blobs_.Put(job_id_, name, bytes));
    {
      std::lock_guard lock(mutex_);
      if (std::find(names_.begin(), names_.end(), name) == names_.end()) names_.emplace_back(name);
      sizes_[std::string(name)] = static_cast<int64_t>(bytes.size());
    }
    if (MeshPartOf(name) >= 0) publish_(std::string(name));  // Stored whole first: fetchable now.
    return absl::OkStatus();
  }
  absl::StatusOr<std::string> Read(std::string_view name) const override {
    {
      std::lock_guard lock(mutex_);
      if (!sizes_.contains(std::string(name))) {
        return absl::NotFoundError(core::StrCat("this run wrote no artifact '", name, "'"));
      }
    }
    return blobs_.Read(job_id_, name);
  }
  std::vector<std::string> names() const {
    std::lock_guard lock(mutex_);
    return names_;
  }
  int64_t bytes() const {  // Of the artifacts as last written.
    std::lock_guard lock(mutex_);
    int64_t total = 0;
    for (const auto& [name, size] : sizes_) total += size;
    return total;
  }

 private:
  BlobStore& blobs_;
  std::string job_id_;
  Admit admit_;
  Publish publish_;
  mutable std::mutex mutex_;
  std::vector<std::string> names_;
  std::map<std::string, int64_t> sizes_;
};

namespace {

// Progress of a running job, published to watchers at most every half percent, and written to
// a shared store (for the other services' watchers) at most twice a second.
class RunContext : public core::JobContext {
 public:
  RunContext(JobTable& table, bool shared_store, JobEvents* events, std::shared_ptr<JobEntry> entry, std::string method)
      : table_(table),
        shared_store_(shared_store),
        events_(events),
        entry_(std::move(entry)),
        method_(std::move(method)) {}
  void ReportProgress(std::string_view stage, double fraction) override {
    std::lock_guard lock(mutex_);
    if (stage == last_stage_ && std::abs(fraction - last_fraction_) < 0.005) return;
    const auto now = std::chrono::steady_clock::now();
    if (stage != last_stage_) EndStage(now);
    last_stage_.assign(stage);
    last_fraction_ = fraction;
    const bool persist = shared_store_ && now - last_persisted_ >= std::chrono::milliseconds(500);
    if (persist) last_persisted_ = now;
    table_.Update(
        entry_,
        [&](JobRecord& r) {
          r.stage = last_stage_;
          // Never backwards, whatever share an engine's later stage was given: a user reads
          // progress as how much of the job is done.
          r.progress = std::max(r.progress, std::clamp(fraction, 0.0, 1.0));
        },
        persist);
  }
  bool IsCancelled() const override {
    return entry_->cancel_requested.load() || entry_->interrupted.load() || entry_->lost.load();
  }
  // Reports the stage in progress as ended (at the end of the run).
  void Finish() {
    std::lock_guard lock(mutex_);
    EndStage(std::chrono::steady_clock::now());
    last_stage_.clear();
  }

 private:
  void EndStage(std::chrono::steady_clock::time_point now) {  // mutex_ held.
    if (!last_stage_.empty() && events_ != nullptr) {
      events_->StageEnded(method_, last_stage_, std::chrono::duration<double>(now - stage_start_).count());
    }
    stage_start_ = now;
  }

  JobTable& table_;
  const bool shared_store_;
  JobEvents* const events_;
  std::shared_ptr<JobEntry> entry_;
  const std::string method_;
  std::mutex mutex_;
  std::string last_stage_;
  double last_fraction_ = -1;
  std::chrono::steady_clock::time_point last_persisted_{};
  std::chrono::steady_clock::time_point stage_start_ = std::chrono::steady_clock::now();
};

}  // namespace

ClaimScope JobRunner::Scope(const std::string& parent) const {
  return {TileChildFormat(options_.tile_format != 0 ? options_.tile_format : pu::kTileFormat), parent};
}

std::shared_ptr<JobEntry> JobRunner::ClaimNext(const ClaimScope& scope, std::shared_ptr<DecodedInput>* decoded) {
  auto claimed = parts_.store.Claim(runner_, options_.lease, scope);
  if (!claimed.ok()) {
    // Once per outage, not at every poll of every worker.
    if (!claims_failing_.exchange(true))
      spdlog::error("cannot take jobs from the store: {}", claimed.status().ToString());
    return nullptr;
  }
  claims_failing_ = false;
  if (!claimed->has_value()) return nullptr;
  *decoded = parts_.decoded.Take((*claimed)->id);
  return parts_.table.Hold(**std::move(claimed));
}

void JobRunner::Start() {
  for (int i = 0; i < options_.workers; ++i) workers_.emplace_back([this] { WorkerLoop(); });
}

void JobRunner::Stop() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  work_available_.notify_all();
  for (auto& t : workers_) t.join();
  workers_.clear();
}

void JobRunner::WakeWorkers() {
  {
    std::lock_guard lock(mutex_);
    ++work_signal_;
  }
  work_available_.notify_all();
}

void JobRunner::WorkerLoop() {
  for (;;) {
    uint64_t signal = 0;
    {
      std::lock_guard lock(mutex_);
      if (stop_) return;
      signal = work_signal_;
    }
    // The tiles of a build that has begun come before a new job (Scope), so that it finishes first.
    std::shared_ptr<DecodedInput> decoded;
    if (std::shared_ptr<JobEntry> entry = ClaimNext(Scope(), &decoded)) {
      RunJob(entry, std::move(decoded));
      continue;
    }
    // Nothing to claim: wait for a submission, another service's job, or the next poll.
    std::unique_lock lock(mutex_);
    const auto woken = [&] { return stop_ || work_signal_ != signal; };
    // A store of its own gets jobs only through Submit; the long wait there only guards
    // against a claim that failed.
    work_available_.wait_for(lock, parts_.store.shared() ? options_.poll : std::chrono::milliseconds(10'000), woken);
  }
}

TileJobs JobRunner::TileJobsOf() {
  TileJobs jobs;
  jobs.get = [this](const std::string& id) { return parts_.table.Get(id); };
  jobs.children = [this](const std::string& parent) { return parts_.table.Children(parent); };
  jobs.any_queued = [this](const std::string& parent) {
    return !parts_.table
                .Children(
                    parent, [](const JobRecord& r) { return r.state == JobState::kQueued; }, 1)
                .empty();
  };
  jobs.run_one = [this](const std::string& parent) -> absl::StatusOr<bool> {
    std::shared_ptr<DecodedInput> none;
    std::shared_ptr<JobEntry> entry = ClaimNext(Scope(parent), &none);
    if (entry == nullptr) return false;
    RunJob(entry, nullptr);
    return true;
  };
  jobs.wait = [this, seen = uint64_t{0}](std::chrono::milliseconds timeout) mutable {
    seen = parts_.table.WaitForAnyChange(seen, timeout);
  };
  jobs.wait_limit = options_.lease;
  jobs.child_format = Scope().child_format;
  return jobs;
}

absl::StatusOr<Statistics> JobRunner::RunTile(const std::shared_ptr<JobEntry>& entry, const JobRecord& record) {
  RunContext ctx(parts_.table, parts_.store.shared(), options_.events.get(), entry, record.spec.method);
  struct StageEnd {
    RunContext& ctx;
    ~StageEnd() { ctx.Finish(); }
  } stage_end{ctx};
  const auto parent_running = [this, &record] {
    auto parent = parts_.store.Get(record.parent);
    return parent.ok() && parent->state == JobState::kRunning;
  };
  const auto start = std::chrono::steady_clock::now();
  LSQSURF_RETURN_IF_ERROR(RunTileJob(parts_.blobs, record, ctx, parent_running));
  spdlog::info("[job {}] tile {} made here in {:.2f} s (attempt {})", record.parent, record.child_index,
               core::SecondsSince(start), record.attempts);
  return Statistics{};
}

absl::StatusOr<Statistics> JobRunner::RunKind(const std::shared_ptr<JobEntry>& entry, BlobSink& sink,
                                              std::shared_ptr<DecodedInput> decoded) {
  // The run works on its own copy: the record is replaced whenever its state is stored.
  const JobRecord record = parts_.table.Snapshot(*entry);
  if (IsChildJob(record)) return RunTile(entry, record);
  Uploads uploads;
  // A decoded input stands in for the uploads; without one they are read back.
  auto read_back = [&](const std::string& slot) -> absl::StatusOr<bool> {
    const std::string blob = UploadBlob(slot);
    if (!parts_.blobs.Exists(record.id, blob)) return false;
    auto bytes = parts_.blobs.Map(record.id, blob);
    if (!bytes.ok()) return bytes.status();
    uploads[slot] = *std::move(bytes);
    return true;
  };
  for (const auto& [slot, blob] : UploadFiles()) {
    if (decoded != nullptr) break;
    if (auto read = read_back(slot); !read.ok()) return read.status();
  }
  // The input's further parts, up to the first missing.
  for (int64_t part = 1; decoded == nullptr && uploads.contains(kInputUpload) && part < kMaxInputParts; ++part) {
    auto read = read_back(InputPartSlot(part));
    if (!read.ok()) return read.status();
    if (!*read) break;
  }
  RunContext ctx(parts_.table, parts_.store.shared(), options_.events.get(), entry, record.spec.method);
  struct StageEnd {
    RunContext& ctx;
    ~StageEnd() { ctx.Finish(); }
  } stage_end{ctx};
  const JobKind* kind = KindFor(options_.kind_overrides, record.spec.method);
  if (kind == nullptr) return absl::FailedPreconditionError(core::StrCat("no method '", record.spec.method, "'"));
  // Only the jobs the spec names, whose visibility to the submitter Submit checked.
  const std::vector<std::string> referenced = kind->ReferencedJobs(record.spec);
  RunEnvironment env{sink,
                     ctx,
                     &parts_.pictures.renderer(),
                     std::move(decoded),
                     [this, referenced](const std::string& id, const std::string& name) -> absl::StatusOr<std::string> {
                       if (std::find(referenced.begin(), referenced.end(), id) == referenced.end())
                         return NoSuchJob(id);
                       auto reader = OpenJobResult(parts_.table, parts_.blobs, id, name);
                       if (!reader.ok()) return reader.status();
                       return ReadAll(**reader);
                     },
                     options_.max_job_memory,
                     scratch_dir_};
  std::optional<StoreTileExchange> tiles;
  if (parts_.store.shared()) {
    tiles.emplace(parts_.store, parts_.blobs, record, TileJobsOf());
    env.tiles = &*tiles;
  }
  return core::CatchEngineErrors("job", [&] { return kind->Run(record.spec, uploads, env); });
}

void JobRunner::RunJob(const std::shared_ptr<JobEntry>& entry, std::shared_ptr<DecodedInput> decoded) {
  const std::string id = entry->record.id;
  const auto run_start = std::chrono::steady_clock::now();
  if (entry->record.state == JobState::kFailed) {
    // Its stored spec no longer decodes here: the claim read it back failed, with the reason.
    parts_.table.Update(entry, [](JobRecord&) {});
  } else {
    spdlog::info("[job {}] started (attempt {})", id, entry->record.attempts);
    const auto start = std::chrono::steady_clock::now();
    BlobSink sink(
        parts_.blobs, id,
        [this, &entry](int64_t artifact_bytes) { return parts_.admission.AdmitResults(entry, artifact_bytes); },
        [this, &entry](const std::string& name) {
          parts_.table.Update(entry, [&](JobRecord& r) {
            if (std::find(r.results.begin(), r.results.end(), name) == r.results.end()) r.results.push_back(name);
          });
        });
    absl::StatusOr<Statistics> result = RunKind(entry, sink, std::move(decoded));
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (entry->lost) {
      spdlog::warn("[job {}] ran {:.2f} s under a lapsed lease; its outcome is dropped", id, seconds);
      // Should the store still show it as this server's, it goes back to the queue, not held
      // against it; otherwise the write is refused and the store's state stands.
      parts_.table.Update(entry, [](JobRecord& r) {
        r.state = JobState::kQueued;
        r.stage.clear();
        r.progress = 0;
        r.results.clear();  // Published parts: the next run publishes them again.
        ++r.interruptions;
      });
    } else if (result.ok()) {
      parts_.table.Update(entry, [&](JobRecord& r) {
        r.state = JobState::kSucceeded;
        r.stage = "done";
        r.progress = 1;
        r.statistics = *std::move(result);
        r.statistics.emplace_back("wall_seconds", seconds);
        r.results = sink.names();
        r.stored_bytes = r.input_bytes + SpecBytes(r.spec) + sink.bytes();
      });
      spdlog::info("[job {}] succeeded in {:.2f} s", id, seconds);
    } else if (entry->interrupted && !entry->cancel_requested &&
               result.status().code() == absl::StatusCode::kCancelled) {
      // Interrupted by a shutdown, and nobody asked to cancel it: it runs again later.
      parts_.table.Update(entry, [](JobRecord& r) {
        r.state = JobState::kQueued;
        r.stage.clear();
        r.progress = 0;
        r.results.clear();
        ++r.interruptions;  // A shutdown is not the job's fault.
      });
      spdlog::info("[job {}] interrupted by shutdown; will resume on restart", id);
    } else if (result.status().code() == absl::StatusCode::kCancelled) {
      // What it wrote stays with it (until it is deleted), so it counts as stored.
      parts_.table.Update(entry, [&](JobRecord& r) {
        r.state = JobState::kCancelled;
        r.error = "cancelled by request";
        r.cancel_requested = false;
        r.stored_bytes = r.input_bytes + SpecBytes(r.spec) + sink.bytes();
      });
      spdlog::info("[job {}] cancelled after {:.2f} s", id, seconds);
    } else {
      // The reason may quote what the user sent (a CSG expression, a file's own text): kept
      // bounded and with its control bytes escaped, in the record as in the log, where a
      // newline would forge a line.
      const std::string reason = core::Printable(std::string(result.status().message()), kMaxJobErrorBytes);
      parts_.table.Update(entry, [&](JobRecord& r) {
        r.state = JobState::kFailed;
        r.error = reason;
        r.stored_bytes = r.input_bytes + SpecBytes(r.spec) + sink.bytes();
      });
      spdlog::warn("[job {}] failed ({}): {}", id, absl::StatusCodeToString(result.status().code()), reason);
    }
  }
  if (options_.events != nullptr) {
    const JobRecord ended = parts_.table.Snapshot(*entry);
    options_.events->JobEnded(ended.spec.method, ended.state,
                              std::chrono::duration<double>(std::chrono::steady_clock::now() - run_start).count());
  }
  parts_.table.Release(entry);
}

}  // namespace lsqsurf::jobs
