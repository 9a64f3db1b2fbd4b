#include "worker/jobs/job_service.h"

#include <spdlog/spdlog.h>

#include <cmath>
#include <filesystem>
#include <random>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/volume_job.h"
#include "worker/render/render.h"

namespace lsqsurf::jobs {
namespace {

// Where each upload slot is kept in a job's folder (names kept from earlier versions).
const std::map<std::string, std::string>& UploadFiles() {
  static const auto* files = new std::map<std::string, std::string>{
      {kInputUpload, "input.drc"}, {kVelocityUpload, "velocity.vtk"}, {kCellsUpload, "cells.lqc"}};
  return *files;
}

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string NewJobId() {
  static std::mutex mutex;
  static std::mt19937_64 rng(std::random_device{}());
  std::lock_guard lock(mutex);
  return fmt::format("{:016x}", rng());
}

absl::Status NoJob(const std::string& id) { return absl::NotFoundError(core::StrCat("no job with id '", id, "'")); }

}  // namespace

// Writes a job's artifacts into the blob store, recording their names in order.
class BlobSink final : public ArtifactSink {
 public:
  BlobSink(BlobStore& blobs, std::string job_id) : blobs_(blobs), job_id_(std::move(job_id)) {}
  absl::Status Write(std::string_view name, std::string_view bytes) override {
    LSQSURF_RETURN_IF_ERROR(blobs_.Put(job_id_, name, bytes));
    std::lock_guard lock(mutex_);
    if (std::find(names_.begin(), names_.end(), name) == names_.end()) names_.emplace_back(name);
    return absl::OkStatus();
  }
  std::vector<std::string> names() const {
    std::lock_guard lock(mutex_);
    return names_;
  }

 private:
  BlobStore& blobs_;
  std::string job_id_;
  mutable std::mutex mutex_;
  std::vector<std::string> names_;
};

struct JobService::Entry {
  JobRecord record;
  std::shared_ptr<void> decoded;   // The kind's decoded input while queued; guarded by mutex_.
  uint64_t persisted_version = 0;  // Guarded by the service's store_mutex_.
  std::atomic<bool> cancel_requested{false};
  std::atomic<bool> interrupted{false};  // Shutdown: re-queue rather than cancel.
};

// Progress of a running job, published to watchers at most every half percent.
class JobService::Context : public core::JobContext {
 public:
  Context(JobService& service, std::shared_ptr<Entry> entry) : service_(service), entry_(std::move(entry)) {}
  void ReportProgress(std::string_view stage, double fraction) override {
    std::lock_guard lock(mutex_);
    if (stage == last_stage_ && std::abs(fraction - last_fraction_) < 0.005) return;
    last_stage_.assign(stage);
    last_fraction_ = fraction;
    service_.Update(
        entry_,
        [&](JobRecord& r) {
          r.stage = last_stage_;
          r.progress = std::clamp(fraction, 0.0, 1.0);
        },
        /*persist=*/false);
  }
  bool IsCancelled() const override { return entry_->cancel_requested.load() || entry_->interrupted.load(); }

 private:
  JobService& service_;
  std::shared_ptr<Entry> entry_;
  std::mutex mutex_;
  std::string last_stage_;
  double last_fraction_ = -1;
};

JobService::JobService(JobServiceOptions options)
    : options_(std::move(options)), renderer_(std::make_unique<render::SharedRenderer>()) {}

absl::StatusOr<std::unique_ptr<JobService>> JobService::Open(const JobServiceOptions& options) {
  if (options.data_dir.empty()) return absl::InvalidArgumentError("a data directory is required");
  if (options.workers < 1 || options.max_queue < 1 || options.max_renders < 1) {
    return absl::InvalidArgumentError("workers, max_queue and max_renders must be at least 1");
  }
  std::error_code ec;
  std::filesystem::create_directories(options.data_dir, ec);
  if (ec) {
    return absl::UnavailableError(core::StrCat("cannot create data directory ", options.data_dir, ": ", ec.message()));
  }
  std::unique_ptr<JobService> service(new JobService(options));
  if (options.blobs != nullptr) {
    service->blobs_ = options.blobs;
  } else {
    auto blobs = LocalDirBlobStore::Open((std::filesystem::path(options.data_dir) / "jobs").string());
    if (!blobs.ok()) return blobs.status();
    service->blobs_ = *std::move(blobs);
  }
  auto store = SqliteJobStore::Open((std::filesystem::path(options.data_dir) / "jobs.db").string());
  if (!store.ok()) return store.status();
  service->store_ = *std::move(store);
  auto records = service->store_->LoadAll();
  if (!records.ok()) return records.status();
  for (JobRecord& r : *records) {
    auto entry = std::make_shared<Entry>();
    if (r.state == JobState::kRunning) {
      // The server died while this job ran (a graceful stop re-queues first): a crash.
      if (r.attempts - r.interruptions >= options.max_attempts) {
        r.state = JobState::kFailed;
        r.error = core::StrCat("the server stopped while this job was running, ", r.attempts - r.interruptions,
                               " times; giving up (the input may crash the engine)");
        spdlog::warn("[job {}] failed on recovery: {}", r.id, r.error);
      } else {
        r.state = JobState::kQueued;
        spdlog::info("[job {}] re-queued after an interrupted run", r.id);
      }
      r.stage.clear();
      r.progress = 0;
      r.updated_ms = NowMs();
      if (absl::Status s = service->store_->Put(r); !s.ok()) return s;
    }
    entry->record = std::move(r);
    if (entry->record.state == JobState::kQueued) service->queue_.push_back(entry);
    service->jobs_[entry->record.id] = entry;
  }
  spdlog::info("job service: {} jobs on record, {} queued, {} workers, data in {}", service->jobs_.size(),
               service->queue_.size(), options.workers, options.data_dir);
  for (int i = 0; i < options.workers; ++i) service->workers_.emplace_back([s = service.get()] { s->WorkerLoop(); });
  return service;
}

JobService::~JobService() { Shutdown(); }

const JobKind* JobService::KindOf(const std::string& method) const {
  if (auto it = options_.kind_overrides.find(method); it != options_.kind_overrides.end()) return it->second;
  const MethodEntry* m = FindMethod(method);
  return m ? m->kind : nullptr;
}

absl::StatusOr<JobRecord> JobService::Submit(const JobSpec& spec, Uploads uploads) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpec(spec));
  if (spec.preview.enabled) {
    if (auto r = renderer_->Get(); !r.ok()) {
      return absl::UnavailableError(
          core::StrCat("this server cannot draw previews (", r.status().message(), "); submit the job without one"));
    }
  }
  const MethodEntry* method = FindMethod(spec.method);
  int64_t bytes = 0;
  for (auto it = uploads.begin(); it != uploads.end();) {
    if (it->second.empty()) {
      it = uploads.erase(it);
      continue;
    }
    const auto& accepted = method->info.uploads;
    if (std::find(accepted.begin(), accepted.end(), it->first) == accepted.end()) {
      return absl::InvalidArgumentError(core::StrCat("the ", spec.method, " method takes no '", it->first, "' upload"));
    }
    bytes += static_cast<int64_t>(it->second.size());
    ++it;
  }
  if (bytes > options_.max_input_bytes) {
    return absl::ResourceExhaustedError(
        core::StrCat("the upload has ", bytes, " bytes; this server accepts at most ", options_.max_input_bytes));
  }
  auto checked =
      KindOf(spec.method)->CheckUploads(spec, uploads, {options_.max_points, options_.min_points, options_.max_cells});
  if (!checked.ok()) return checked.status();
  {
    std::lock_guard lock(mutex_);
    if (shutting_down_) return absl::UnavailableError("the server is shutting down");
    if (static_cast<int>(queue_.size()) >= options_.max_queue) {
      return absl::ResourceExhaustedError(
          core::StrCat("the job queue is full (", queue_.size(), " jobs waiting); try again later"));
    }
  }
  auto entry = std::make_shared<Entry>();
  JobRecord& r = entry->record;
  r.id = NewJobId();
  r.spec = spec;
  r.created_ms = r.updated_ms = NowMs();
  r.input_points = checked->points;
  r.input_bytes = bytes;
  for (const auto& [slot, data] : uploads) {
    if (absl::Status s = blobs_->Put(r.id, UploadFiles().at(slot), data); !s.ok()) {
      (void)blobs_->RemoveJob(r.id);
      return s;
    }
  }
  // Durable before it is visible: a job the caller hears of is on disk.
  {
    std::lock_guard store_lock(store_mutex_);
    if (absl::Status s = store_->Put(r); !s.ok()) {
      (void)blobs_->RemoveJob(r.id);
      return s;
    }
  }
  std::unique_lock lock(mutex_);
  if (shutting_down_ || static_cast<int>(queue_.size()) >= options_.max_queue) {
    const bool stopping = shutting_down_;
    lock.unlock();
    std::lock_guard store_lock(store_mutex_);
    (void)store_->Remove(r.id);
    (void)blobs_->RemoveJob(r.id);
    return stopping ? absl::UnavailableError("the server is shutting down")
                    : absl::ResourceExhaustedError("the job queue is full; try again later");
  }
  // The decoded input waits with the job while the waiting ones hold at most max_points points.
  if (checked->decoded != nullptr && decoded_points_ + r.input_points <= options_.max_points) {
    entry->decoded = std::move(checked->decoded);
    decoded_points_ += r.input_points;
  }
  jobs_[r.id] = entry;
  queue_.push_back(entry);
  work_available_.notify_one();
  spdlog::info("[job {}] accepted: method {}, {} points, {} bytes", r.id, spec.method, r.input_points, r.input_bytes);
  return r;
}

absl::StatusOr<JobRecord> JobService::Get(const std::string& id) const {
  std::lock_guard lock(mutex_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return NoJob(id);
  return it->second->record;
}

std::vector<JobRecord> JobService::List() const {
  std::lock_guard lock(mutex_);
  std::vector<JobRecord> out;
  for (const auto& [id, e] : jobs_) out.push_back(e->record);
  std::sort(out.begin(), out.end(), [](const JobRecord& a, const JobRecord& b) {
    return a.created_ms != b.created_ms ? a.created_ms > b.created_ms : a.id > b.id;
  });
  return out;
}

void JobService::Update(const std::shared_ptr<Entry>& entry, const std::function<void(JobRecord&)>& change,
                        bool persist) {
  JobRecord copy;
  {
    std::lock_guard lock(mutex_);
    change(entry->record);
    entry->record.updated_ms = NowMs();
    ++entry->record.version;
    if (persist) copy = entry->record;
  }
  changed_.notify_all();
  if (persist) Persist(entry, copy);
}

void JobService::Persist(const std::shared_ptr<Entry>& entry, const JobRecord& copy) {
  std::lock_guard store_lock(store_mutex_);
  // Writes of one job may arrive out of order from two threads: the newest wins.
  if (copy.version <= entry->persisted_version) return;
  entry->persisted_version = copy.version;
  if (absl::Status s = store_->Put(copy); !s.ok())
    spdlog::error("[job {}] cannot persist state: {}", copy.id, s.ToString());
}

absl::StatusOr<JobRecord> JobService::Cancel(const std::string& id) {
  std::shared_ptr<Entry> entry;
  {
    std::lock_guard lock(mutex_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return NoJob(id);
    entry = it->second;
    if (IsTerminal(entry->record.state)) {
      return absl::FailedPreconditionError(
          core::StrCat("job ", id, " has already ", JobStateName(entry->record.state)));
    }
    entry->cancel_requested = true;
    auto q = std::find(queue_.begin(), queue_.end(), entry);
    if (q == queue_.end()) {
      spdlog::info("[job {}] cancellation requested while running", id);
      return entry->record;
    }
    queue_.erase(q);
    ReleaseDecoded(*entry);
  }
  Update(entry, [](JobRecord& r) {
    r.state = JobState::kCancelled;
    r.error = "cancelled by request before it started";
  });
  spdlog::info("[job {}] cancelled while queued", id);
  return Get(id);
}

absl::Status JobService::Delete(const std::string& id) {
  {
    std::lock_guard lock(mutex_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return NoJob(id);
    if (!IsTerminal(it->second->record.state)) {
      return absl::FailedPreconditionError(
          core::StrCat("job ", id, " is ", JobStateName(it->second->record.state), "; cancel it before deleting it"));
    }
    jobs_.erase(it);
  }
  {
    std::lock_guard store_lock(store_mutex_);
    if (absl::Status s = store_->Remove(id); !s.ok())
      spdlog::error("[job {}] cannot remove its record: {}", id, s.ToString());
  }
  if (absl::Status s = blobs_->RemoveJob(id); !s.ok()) spdlog::error("[job {}] {}", id, s.ToString());
  changed_.notify_all();
  spdlog::info("[job {}] deleted", id);
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<BlobReader>> JobService::OpenResult(const std::string& id,
                                                                   const std::string& name) const {
  auto r = Get(id);
  if (!r.ok()) return r.status();
  if (r->state != JobState::kSucceeded) {
    return absl::FailedPreconditionError(
        core::StrCat("job ", id, " is ", JobStateName(r->state), "; results exist only for succeeded jobs"));
  }
  const std::string artifact = name.empty() && !r->results.empty() ? r->results.front() : name;
  if (std::find(r->results.begin(), r->results.end(), artifact) == r->results.end()) {
    std::string names;
    for (const auto& n : r->results) core::StrAppend(&names, names.empty() ? "" : ", ", n);
    return absl::NotFoundError(core::StrCat("job ", id, " has no result '", artifact, "'; it has: ", names));
  }
  return blobs_->Open(id, artifact);
}

absl::StatusOr<RenderedPicture> JobService::Render(const std::string& id, const std::string& name,
                                                   const core::ParamSet& view) {
  const auto* params = view.As<render::RenderParams>();
  if (params == nullptr) return absl::InternalError("view options of another type");
  // Checked before any file is read or a context is made.
  LSQSURF_RETURN_IF_ERROR(render::Validate(*params));
  if (renders_.fetch_add(1) >= options_.max_renders) {
    renders_.fetch_sub(1);
    return absl::ResourceExhaustedError(
        core::StrCat(options_.max_renders, " pictures are being drawn already; try again shortly"));
  }
  struct Release {
    std::atomic<int>& n;
    ~Release() { n.fetch_sub(1); }
  } release{renders_};
  auto reader = OpenResult(id, name);
  if (!reader.ok()) return reader.status();
  auto read = ReadAll(**reader);
  if (!read.ok()) return read.status();
  const std::string& bytes = *read;
  if (volume::IsStoredVolumeField(bytes)) return RenderVolumeField(id, bytes, *params);
  auto geometry = io::PeekDracoGeometry(bytes);
  if (!geometry.ok()) {
    return absl::InvalidArgumentError(
        core::StrCat("artifact '", name, "' is not a Draco mesh or point set; only those can be rendered"));
  }
  auto renderer = renderer_->Get();
  if (!renderer.ok()) return renderer.status();
  render::RenderInfo info;
  absl::StatusOr<render::Image> image = absl::InvalidArgumentError("");
  if (*geometry == io::DracoGeometry::kTriangleMesh) {
    auto mesh = io::DecodeDracoMesh(bytes);
    if (!mesh.ok()) return mesh.status();
    image = (*renderer)->RenderMesh(*mesh, *params, &info);
  } else {
    auto cloud = io::DecodeDracoPointCloud(bytes);
    if (!cloud.ok()) return cloud.status();
    image = (*renderer)->RenderPoints(*cloud, *params, &info);
  }
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return RenderedPicture{*std::move(png), info.color_min, info.color_max, info.renderer};
}

absl::StatusOr<RenderedPicture> JobService::RenderVolumeField(const std::string& id, const std::string& bytes,
                                                              const render::RenderParams& params) {
  // The sampled grid of the last job drawn is kept: the frames of a turntable share it.
  const std::string key = core::StrCat(id, "/", params.volume_resolution);
  std::shared_ptr<const SampledVolume> sampled;
  {
    std::lock_guard lock(volume_mutex_);
    if (volume_key_ == key) sampled = volume_grid_;
  }
  if (sampled == nullptr) {
    auto field = volume::DeserializeVolumeField(bytes);
    if (!field.ok()) return field.status();
    auto grid = SampleVolumeForPicture(**field, params.volume_resolution);
    if (!grid.ok()) return grid.status();
    sampled = std::make_shared<const SampledVolume>(*std::move(grid));
    std::lock_guard lock(volume_mutex_);
    volume_key_ = key;
    volume_grid_ = sampled;
  }
  // The GL's shader on a GPU; on Mesa's software rasterizer (or without a GL) the C++ ray
  // caster, which draws the same picture twice as fast there (measured: 0.24 s against 0.53 s
  // for 512² frames of the 384k-tetrahedra Marschner–Lobb mesh).
  render::RenderInfo info;
  auto renderer = renderer_->Get();
  const bool gpu = renderer.ok() && (*renderer)->description().find("llvmpipe") == std::string::npos &&
                   (*renderer)->description().find("softpipe") == std::string::npos;
  auto image = gpu ? (*renderer)->RenderVolume(sampled->grid, params, &info)
                   : render::RaycastVolume(sampled->grid, params, &info);
  if (!image.ok()) return image.status();
  auto png = render::EncodePng(*image);
  if (!png.ok()) return png.status();
  return RenderedPicture{*std::move(png), info.color_min,     info.color_max,
                         info.renderer,   sampled->rms_error, sampled->max_error};
}

bool JobService::CanRender() { return renderer_->Get().ok(); }

absl::StatusOr<JobRecord> JobService::WaitForChange(const std::string& id, uint64_t seen_version,
                                                    std::chrono::milliseconds timeout) const {
  std::unique_lock lock(mutex_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return NoJob(id);
  std::shared_ptr<Entry> entry = it->second;
  changed_.wait_for(lock, timeout,
                    [&] { return entry->record.version != seen_version || shutting_down_ || !jobs_.contains(id); });
  if (!jobs_.contains(id)) return absl::NotFoundError(core::StrCat("job '", id, "' was deleted"));
  return entry->record;
}

void JobService::Shutdown() {
  {
    std::lock_guard lock(mutex_);
    if (shutting_down_ && workers_.empty()) return;
    shutting_down_ = true;
    for (auto& [id, e] : jobs_) {
      if (e->record.state == JobState::kRunning) e->interrupted = true;
    }
  }
  work_available_.notify_all();
  changed_.notify_all();
  for (auto& t : workers_) t.join();
  workers_.clear();
}

std::shared_ptr<void> JobService::ReleaseDecoded(Entry& entry) {
  if (entry.decoded != nullptr) decoded_points_ -= entry.record.input_points;
  return std::move(entry.decoded);
}

void JobService::WorkerLoop() {
  for (;;) {
    std::shared_ptr<Entry> entry;
    std::shared_ptr<void> decoded;
    {
      std::unique_lock lock(mutex_);
      work_available_.wait(lock, [&] { return shutting_down_ || !queue_.empty(); });
      if (shutting_down_) return;
      entry = queue_.front();
      queue_.pop_front();
      decoded = ReleaseDecoded(*entry);
    }
    RunJob(entry, std::move(decoded));
  }
}

absl::StatusOr<Statistics> JobService::RunKind(const std::shared_ptr<Entry>& entry, BlobSink& sink,
                                               std::shared_ptr<void> decoded) {
  const JobRecord& record = entry->record;  // Only this worker changes spec and id.
  Uploads uploads;
  // A decoded input stands in for the uploads; without one they are read back.
  for (const auto& [slot, blob] : UploadFiles()) {
    if (decoded != nullptr) break;
    if (!blobs_->Exists(record.id, blob)) continue;
    auto bytes = blobs_->Read(record.id, blob);
    if (!bytes.ok()) return bytes.status();
    uploads[slot] = *std::move(bytes);
  }
  const JobKind* kind = KindOf(record.spec.method);
  if (kind == nullptr) return absl::FailedPreconditionError(core::StrCat("no method '", record.spec.method, "'"));
  Context ctx(*this, entry);
  RunEnvironment env{sink, ctx, renderer_.get(), std::move(decoded),
                     [this](const std::string& id, const std::string& name) -> absl::StatusOr<std::string> {
                       auto reader = OpenResult(id, name);
                       if (!reader.ok()) return reader.status();
                       return ReadAll(**reader);
                     }};
  try {
    return kind->Run(record.spec, uploads, env);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("the job ran out of memory");
  } catch (const std::exception& e) {
    return absl::InternalError(core::StrCat("engine error: ", e.what()));
  }
}

void JobService::RunJob(const std::shared_ptr<Entry>& entry, std::shared_ptr<void> decoded) {
  const std::string id = entry->record.id;
  Update(entry, [](JobRecord& r) {
    r.state = JobState::kRunning;
    r.stage = "starting";
    r.progress = 0;
    ++r.attempts;
  });
  spdlog::info("[job {}] started (attempt {})", id, entry->record.attempts);
  const auto start = std::chrono::steady_clock::now();
  BlobSink sink(*blobs_, id);
  absl::StatusOr<Statistics> result = RunKind(entry, sink, std::move(decoded));
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (result.ok()) {
    Update(entry, [&](JobRecord& r) {
      r.state = JobState::kSucceeded;
      r.stage = "done";
      r.progress = 1;
      r.statistics = *std::move(result);
      r.statistics.emplace_back("wall_seconds", seconds);
      r.results = sink.names();
    });
    spdlog::info("[job {}] succeeded in {:.2f} s", id, seconds);
  } else if (entry->interrupted && result.status().code() == absl::StatusCode::kCancelled) {
    Update(entry, [](JobRecord& r) {
      r.state = JobState::kQueued;
      r.stage.clear();
      r.progress = 0;
      ++r.interruptions;  // A shutdown is not the job's fault.
    });
    spdlog::info("[job {}] interrupted by shutdown; will resume on restart", id);
  } else if (result.status().code() == absl::StatusCode::kCancelled) {
    Update(entry, [](JobRecord& r) {
      r.state = JobState::kCancelled;
      r.error = "cancelled by request";
    });
    spdlog::info("[job {}] cancelled after {:.2f} s", id, seconds);
  } else {
    Update(entry, [&](JobRecord& r) {
      r.state = JobState::kFailed;
      r.error = std::string(result.status().message());
    });
    spdlog::warn("[job {}] failed: {}", id, result.status().ToString());
  }
}

}  // namespace lsqsurf::jobs
