#include "worker/jobs/job_service.h"

#include <spdlog/spdlog.h>

#include <atomic>
#include <cmath>
#include <filesystem>
#include <optional>
#include <random>

#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/io/vtk_grid.h"
#include "worker/jobs/front_job.h"
#include "worker/jobs/pictures.h"

namespace lsqsurf::jobs {
namespace {

constexpr char kInputFile[] = "input.drc";
constexpr char kVelocityFile[] = "velocity.vtk";
constexpr char kMeshArtifact[] = "mesh.drc";
constexpr char kPreviewArtifact[] = "preview.png";

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string NewJobId() {
  static std::mutex mutex;
  static std::mt19937_64 rng(std::random_device{}());
  std::lock_guard lock(mutex);
  return fmt::format("{:016x}", rng());
}

// Checks the pictures a job asks for: a view the renderer accepts, a colour the method's
// results carry, a finite turntable step.
absl::Status ValidatePreview(const JobSpec& spec) {
  const PreviewSpec& preview = spec.preview;
  if (!preview.enabled) return absl::OkStatus();
  if (absl::Status s = render::Validate(preview.render); !s.ok()) return absl::InvalidArgumentError(core::StrCat("preview: ", s.message()));
  if (!(std::abs(preview.turntable_deg_per_frame) <= 360)) {
    return absl::InvalidArgumentError("preview: turntable_deg_per_frame must be within [-360, 360]");
  }
  const std::string& colour = preview.render.color_attribute;
  if (colour.empty()) return absl::OkStatus();
  std::string known;
  if (const MethodSpec* m = FindMethod(spec.method)) {
    for (const std::string& a : m->attributes) {
      if (a == colour) return absl::OkStatus();
      known += (known.empty() ? "" : ", ") + a;
    }
  }
  return absl::InvalidArgumentError(core::StrCat("preview: the ", spec.method, " method's results have no attribute '",
                                                 colour, "' to colour by; they have: ", known.empty() ? "none" : known));
}

// Checks a decoded upload; the messages tell the user what to fix.
absl::Status ValidateCloud(const core::PointCloud& cloud, const JobSpec& spec,
                           const JobServiceOptions& options) {
  if (cloud.empty()) return absl::InvalidArgumentError("the point cloud is empty");
  if (static_cast<int64_t>(cloud.size()) > options.max_points) {
    return absl::ResourceExhaustedError(core::StrCat("the cloud has ", cloud.size(),
                                                     " points; this server accepts at most ",
                                                     options.max_points));
  }
  if (const int64_t bad = core::FindNonFinite(cloud.positions); bad >= 0) {
    return absl::InvalidArgumentError(core::StrCat("point ", bad, " has a NaN or infinite coordinate"));
  }
  if (cloud.has_normals()) {
    for (size_t i = 0; i < cloud.size(); ++i) {
      const float len = cloud.normals[i].norm();
      if (!std::isfinite(len) || len < 1e-6f) {
        return absl::InvalidArgumentError(core::StrCat("normal ", i, " is zero or not finite"));
      }
    }
  } else if (ParameterOrDefault(spec.method, spec.parameters, "estimate_normals") == 0) {
    return absl::InvalidArgumentError(
        "the cloud has no normals and estimate_normals=0; upload normals or allow estimation");
  }
  if (cloud.size() < 16) {
    return absl::InvalidArgumentError(core::StrCat("the cloud has only ", cloud.size(),
                                                   " points; at least 16 are needed"));
  }
  return absl::OkStatus();
}

}  // namespace

struct JobService::Entry {
  JobRecord record;
  std::atomic<bool> cancel_requested{false};
  std::atomic<bool> interrupted{false};  // Shutdown: re-queue rather than cancel.
};

// Progress of a running job, published to watchers at most every half percent.
class JobService::Context : public core::JobContext {
 public:
  Context(JobService& service, std::shared_ptr<Entry> entry)
      : service_(service), entry_(std::move(entry)) {}
  void ReportProgress(std::string_view stage, double fraction) override {
    std::lock_guard lock(mutex_);
    if (stage == last_stage_ && std::abs(fraction - last_fraction_) < 0.005) return;
    last_stage_.assign(stage);
    last_fraction_ = fraction;
    service_.Update(entry_, [&](JobRecord& r) {
      r.stage = last_stage_;
      r.progress = std::clamp(fraction, 0.0, 1.0);
    }, /*persist=*/false);
  }
  bool IsCancelled() const override {
    return entry_->cancel_requested.load() || entry_->interrupted.load();
  }

 private:
  JobService& service_;
  std::shared_ptr<Entry> entry_;
  std::mutex mutex_;
  std::string last_stage_;
  double last_fraction_ = -1;
};

absl::StatusOr<std::unique_ptr<JobService>> JobService::Open(const JobServiceOptions& options) {
  if (options.data_dir.empty()) return absl::InvalidArgumentError("a data directory is required");
  if (options.workers < 1 || options.max_queue < 1) {
    return absl::InvalidArgumentError("workers and max_queue must be at least 1");
  }
  std::error_code ec;
  std::filesystem::create_directories(std::filesystem::path(options.data_dir) / "jobs", ec);
  if (ec) {
    return absl::UnavailableError(core::StrCat("cannot create data directory ", options.data_dir, ": ", ec.message()));
  }
  std::unique_ptr<JobService> service(new JobService(options));
  auto store = JobStore::Open((std::filesystem::path(options.data_dir) / "jobs.db").string());
  if (!store.ok()) return store.status();
  service->store_ = *std::move(store);
  auto records = service->store_->LoadAll();
  if (!records.ok()) return records.status();
  for (JobRecord& r : *records) {
    auto entry = std::make_shared<Entry>();
    if (r.state == JobState::kRunning) {
      if (r.attempts >= options.max_attempts) {
        r.state = JobState::kFailed;
        r.error = core::StrCat("the server stopped while this job was running, ", r.attempts,
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
  spdlog::info("job service: {} jobs on record, {} queued, {} workers, data in {}",
               service->jobs_.size(), service->queue_.size(), options.workers, options.data_dir);
  for (int i = 0; i < options.workers; ++i) service->workers_.emplace_back([s = service.get()] { s->WorkerLoop(); });
  return service;
}

JobService::~JobService() { Shutdown(); }

std::string JobService::JobDir(const std::string& id) const {
  return (std::filesystem::path(options_.data_dir) / "jobs" / id).string();
}

absl::StatusOr<JobRecord> JobService::Submit(const JobSpec& spec, std::string input, std::string velocity) {
  if (absl::Status s = ValidateRequest(spec.method, spec.parameters); !s.ok()) return s;
  if (spec.mesh_position_bits < 8 || spec.mesh_position_bits > 30) {
    return absl::InvalidArgumentError("mesh_position_bits must be between 8 and 30");
  }
  if (absl::Status s = ValidatePreview(spec); !s.ok()) return s;
  if (spec.preview.enabled) {
    if (auto r = renderer_.Get(); !r.ok()) {
      return absl::UnavailableError(core::StrCat("this server cannot draw previews (", r.status().message(),
                                                 "); submit the job without one"));
    }
  }
  // A front-tracking job of a named shape needs no upload, and ignores one.
  const bool needs_input = spec.method != kTrackMethod || TrackNeedsUpload(spec.parameters);
  if (!needs_input) input.clear();
  if (needs_input && input.empty()) return absl::InvalidArgumentError("no input data was uploaded");
  if (static_cast<int64_t>(input.size() + velocity.size()) > options_.max_input_bytes) {
    return absl::ResourceExhaustedError(core::StrCat("the upload has ", input.size() + velocity.size(),
                                                     " bytes; this server accepts at most ",
                                                     options_.max_input_bytes));
  }
  absl::StatusOr<core::PointCloud> cloud = core::PointCloud{};
  if (needs_input) {
    cloud = io::DecodeDracoPointCloud(input);
    if (!cloud.ok()) return absl::InvalidArgumentError(core::StrCat("input: ", cloud.status().message()));
    if (spec.method == kTrackMethod && !cloud->has_normals()) {
      return absl::InvalidArgumentError("a tracked interface needs oriented normals (outward)");
    }
    if (absl::Status s = ValidateCloud(*cloud, spec, options_); !s.ok()) return s;
  }
  const bool needs_velocity = spec.method == kTrackMethod && TrackNeedsVelocity(spec.parameters);
  if (needs_velocity) {
    if (velocity.empty()) return absl::InvalidArgumentError("field=2 tracks through an uploaded velocity grid, but none was uploaded");
    if (auto grid = io::ParseVtkVectorGrid(velocity, "velocity"); !grid.ok()) return grid.status();
  } else if (!velocity.empty()) {
    return absl::InvalidArgumentError("a velocity grid was uploaded, but only the track method with field=2 uses one");
  }
  {
    std::lock_guard lock(mutex_);
    if (shutting_down_) return absl::UnavailableError("the server is shutting down");
    if (static_cast<int>(queue_.size()) >= options_.max_queue) {
      return absl::ResourceExhaustedError(core::StrCat("the job queue is full (", queue_.size(),
                                                       " jobs waiting); try again later"));
    }
  }
  auto entry = std::make_shared<Entry>();
  JobRecord& r = entry->record;
  r.id = NewJobId();
  r.spec = spec;
  r.created_ms = r.updated_ms = NowMs();
  r.input_points = static_cast<int64_t>(cloud->size());
  r.input_bytes = static_cast<int64_t>(input.size());
  std::error_code ec;
  std::filesystem::create_directories(JobDir(r.id), ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot create the job folder: ", ec.message()));
  if (absl::Status s = io::WriteFileAtomically(JobDir(r.id) + "/" + kInputFile, input); !s.ok()) {
    return absl::UnavailableError(core::StrCat("cannot store the input: ", s.message()));
  }
  if (needs_velocity) {
    if (absl::Status s = io::WriteFileAtomically(JobDir(r.id) + "/" + kVelocityFile, velocity); !s.ok()) {
      std::filesystem::remove_all(JobDir(r.id), ec);
      return absl::UnavailableError(core::StrCat("cannot store the velocity grid: ", s.message()));
    }
  }
  std::lock_guard lock(mutex_);
  if (shutting_down_ || static_cast<int>(queue_.size()) >= options_.max_queue) {
    std::filesystem::remove_all(JobDir(r.id), ec);
    return shutting_down_ ? absl::UnavailableError("the server is shutting down")
                          : absl::ResourceExhaustedError("the job queue is full; try again later");
  }
  if (absl::Status s = store_->Put(r); !s.ok()) {
    std::filesystem::remove_all(JobDir(r.id), ec);
    return s;
  }
  jobs_[r.id] = entry;
  queue_.push_back(entry);
  work_available_.notify_one();
  spdlog::info("[job {}] accepted: method {}, {} points, {} bytes", r.id, spec.method, r.input_points,
               r.input_bytes);
  return r;
}

absl::StatusOr<JobRecord> JobService::Get(const std::string& id) const {
  std::lock_guard lock(mutex_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return absl::NotFoundError(core::StrCat("no job with id '", id, "'"));
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

void JobService::Update(const std::shared_ptr<Entry>& entry,
                        const std::function<void(JobRecord&)>& change, bool persist) {
  JobRecord copy;
  {
    std::lock_guard lock(mutex_);
    change(entry->record);
    entry->record.updated_ms = NowMs();
    ++entry->record.version;
    copy = entry->record;
    if (persist) {
      if (absl::Status s = store_->Put(copy); !s.ok()) {
        spdlog::error("[job {}] cannot persist state: {}", copy.id, s.ToString());
      }
    }
  }
  changed_.notify_all();
}

absl::StatusOr<JobRecord> JobService::Cancel(const std::string& id) {
  std::shared_ptr<Entry> entry;
  {
    std::lock_guard lock(mutex_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return absl::NotFoundError(core::StrCat("no job with id '", id, "'"));
    entry = it->second;
    if (IsTerminal(entry->record.state)) {
      return absl::FailedPreconditionError(core::StrCat("job ", id, " has already ",
                                                        JobStateName(entry->record.state)));
    }
    entry->cancel_requested = true;
    auto q = std::find(queue_.begin(), queue_.end(), entry);
    if (q == queue_.end()) {
      spdlog::info("[job {}] cancellation requested while running", id);
      return entry->record;
    }
    queue_.erase(q);
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
    if (it == jobs_.end()) return absl::NotFoundError(core::StrCat("no job with id '", id, "'"));
    if (!IsTerminal(it->second->record.state)) {
      return absl::FailedPreconditionError(core::StrCat("job ", id, " is ", JobStateName(it->second->record.state),
                                                        "; cancel it before deleting it"));
    }
    if (absl::Status s = store_->Remove(id); !s.ok()) return s;
    jobs_.erase(it);
  }
  std::error_code ec;
  std::filesystem::remove_all(JobDir(id), ec);
  changed_.notify_all();
  spdlog::info("[job {}] deleted", id);
  return absl::OkStatus();
}

absl::StatusOr<std::string> JobService::ResultPath(const std::string& id, const std::string& name) const {
  auto r = Get(id);
  if (!r.ok()) return r.status();
  if (r->state != JobState::kSucceeded) {
    return absl::FailedPreconditionError(core::StrCat("job ", id, " is ", JobStateName(r->state),
                                                      "; results exist only for succeeded jobs"));
  }
  if (std::find(r->results.begin(), r->results.end(), name) == r->results.end()) {
    std::string names;
    for (const auto& n : r->results) names += (names.empty() ? "" : ", ") + n;
    return absl::NotFoundError(core::StrCat("job ", id, " has no result '", name, "'; it has: ", names));
  }
  return JobDir(id) + "/" + name;
}

absl::StatusOr<JobRecord> JobService::WaitForChange(const std::string& id, uint64_t seen_version,
                                                    std::chrono::milliseconds timeout) const {
  std::unique_lock lock(mutex_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return absl::NotFoundError(core::StrCat("no job with id '", id, "'"));
  std::shared_ptr<Entry> entry = it->second;
  changed_.wait_for(lock, timeout, [&] {
    return entry->record.version != seen_version || shutting_down_ || !jobs_.contains(id);
  });
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

void JobService::WorkerLoop() {
  for (;;) {
    std::shared_ptr<Entry> entry;
    {
      std::unique_lock lock(mutex_);
      work_available_.wait(lock, [&] { return shutting_down_ || !queue_.empty(); });
      if (shutting_down_) return;
      entry = queue_.front();
      queue_.pop_front();
    }
    RunJob(entry);
  }
}

void JobService::RunJob(const std::shared_ptr<Entry>& entry) {
  const std::string id = entry->record.id;
  Update(entry, [](JobRecord& r) {
    r.state = JobState::kRunning;
    r.stage = "starting";
    r.progress = 0;
    ++r.attempts;
  });
  spdlog::info("[job {}] started (attempt {})", id, entry->record.attempts);
  const auto start = std::chrono::steady_clock::now();
  absl::StatusOr<SurfaceResult> result = absl::InternalError("not run");
  std::vector<std::string> artifacts = {kMeshArtifact};
  Context ctx(*this, entry);
  try {
    const JobSpec& spec = entry->record.spec;
    auto read_input = [&]() -> absl::StatusOr<core::PointCloud> {
      auto bytes = io::ReadFileBytes(JobDir(id) + "/" + kInputFile);
      if (!bytes.ok()) return bytes.status();
      return io::DecodeDracoPointCloud(*bytes);
    };
    if (spec.method == kTrackMethod) {
      auto uploaded = TrackNeedsUpload(spec.parameters) ? read_input() : core::PointCloud{};
      absl::StatusOr<io::VectorGrid> velocity = io::VectorGrid{};
      if (TrackNeedsVelocity(spec.parameters)) {
        auto bytes = io::ReadFileBytes(JobDir(id) + "/" + kVelocityFile);
        velocity = bytes.ok() ? io::ParseVtkVectorGrid(*bytes, "velocity") : absl::StatusOr<io::VectorGrid>(bytes.status());
      }
      absl::StatusOr<TrackOutput> tracked = absl::InternalError("not run");
      if (!uploaded.ok()) {
        tracked = uploaded.status();
      } else if (!velocity.ok()) {
        tracked = velocity.status();
      } else {
        std::optional<FramePictures> pictures;
        if (spec.preview.enabled) {
          // Without a renderer every picture counts as failed; the frames themselves still come.
          auto r = renderer_.Get();
          if (!r.ok()) spdlog::warn("[job {}] no frame pictures: {}", id, r.status().message());
          pictures = FramePictures{r.ok() ? *r : nullptr, spec.preview.render, spec.preview.turntable_deg_per_frame};
        }
        tracked = RunTrackJob(spec.parameters, &*uploaded, &*velocity, JobDir(id), ctx, pictures ? &*pictures : nullptr);
      }
      if (tracked.ok()) {
        result = SurfaceResult{{}, tracked->statistics};
        artifacts = tracked->artifacts;
      } else {
        result = tracked.status();
      }
    } else {
      auto cloud = read_input();
      result = cloud.ok() ? RunSurfaceMethod(spec.method, spec.parameters, *std::move(cloud), ctx)
                          : absl::StatusOr<SurfaceResult>(cloud.status());
      if (result.ok()) {
        io::DracoOptions draco;
        draco.position_bits = spec.mesh_position_bits;
        auto encoded = io::EncodeDracoMesh(result->mesh, draco);
        if (!encoded.ok()) {
          result = encoded.status();
        } else if (absl::Status s = io::WriteFileAtomically(JobDir(id) + "/" + kMeshArtifact, *encoded); !s.ok()) {
          result = s;
        } else if (spec.preview.enabled) {
          ctx.ReportProgress("drawing the preview", 0.99);
          // A picture that cannot be drawn does not cost the user the mesh: counted, logged.
          auto renderer = renderer_.Get();
          const absl::Status p = renderer.ok() ? WritePicture(**renderer, result->mesh, spec.preview.render,
                                                              JobDir(id) + "/" + kPreviewArtifact)
                                               : renderer.status();
          if (p.ok()) {
            artifacts.push_back(kPreviewArtifact);
          } else {
            spdlog::warn("[job {}] preview failed: {}", id, p.message());
            result->statistics.emplace_back("preview_failures", 1);
          }
        }
      }
    }
  } catch (const std::bad_alloc&) {
    result = absl::ResourceExhaustedError("the job ran out of memory");
  } catch (const std::exception& e) {
    result = absl::InternalError(core::StrCat("engine error: ", e.what()));
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (result.ok()) {
    Update(entry, [&](JobRecord& r) {
      r.state = JobState::kSucceeded;
      r.stage = "done";
      r.progress = 1;
      r.statistics = result->statistics;
      r.statistics.emplace_back("wall_seconds", seconds);
      r.results = artifacts;
    });
    spdlog::info("[job {}] succeeded in {:.2f} s, {} triangles", id, seconds, result->mesh.faces.size());
  } else if (entry->interrupted && result.status().code() == absl::StatusCode::kCancelled) {
    Update(entry, [](JobRecord& r) {
      r.state = JobState::kQueued;
      r.stage.clear();
      r.progress = 0;
      --r.attempts;  // A shutdown is not the job's fault.
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
