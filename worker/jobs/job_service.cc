#include "worker/jobs/job_service.h"

#include <fmt/format.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <random>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_header.h"
#include "worker/jobs/job_admission.h"
#include "worker/jobs/job_ids.h"
#include "worker/jobs/job_pictures.h"
#include "worker/jobs/job_replication.h"
#include "worker/jobs/job_retention.h"
#include "worker/jobs/job_runner.h"
#include "worker/jobs/job_service_internal.h"
#include "worker/jobs/job_table.h"
#include "worker/jobs/method_registry.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::jobs {
namespace {

// The memory this process may use: the machine's, or its container's limit where that is less
// (cgroup v2); 0 when unknown (no limit then).
int64_t PhysicalMemoryBytes() {
  const long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGESIZE);
  int64_t bytes = pages > 0 && page > 0 ? static_cast<int64_t>(pages) * page : 0;
  std::ifstream cgroup("/sys/fs/cgroup/memory.max");
  int64_t limit = 0;
  if (cgroup >> limit && limit > 0) bytes = bytes > 0 ? std::min(bytes, limit) : limit;  // "max" reads as none.
  return bytes;
}

// A runner name unique to this start: a restarted service must not renew the leases of the
// jobs its previous life held.
std::string RunnerName(std::string name) {
  if (name.empty()) {
    char host[256] = {};
    name = gethostname(host, sizeof(host) - 1) == 0 && host[0] != '\0' ? host : "lsqsurfd";
  }
  return fmt::format("{}/{:08x}", name, static_cast<uint32_t>(std::random_device{}()));
}

}  // namespace

const std::map<std::string, std::string>& UploadFiles() {
  static const auto* files = new std::map<std::string, std::string>{
      {kInputUpload, "input.drc"}, {kVelocityUpload, "velocity.vtk"}, {kCellsUpload, "cells.lqc"}};
  return *files;
}

std::string UploadBlob(const std::string& slot) {
  if (const int64_t part = InputPartOf(slot); part > 0) return core::StrCat(slot, ".drc");
  return UploadFiles().at(slot);
}

int64_t SpecBytes(const JobSpec& spec) {
  const auto encoded =
      static_cast<int64_t>(spec.method.size() + spec.params.Encode().size() + spec.preview.view.Encode().size());
  return std::max<int64_t>(0, encoded - kFreeSpecBytes);
}

std::string InputPartSlot(int64_t part) { return part == 0 ? kInputUpload : core::StrCat(kInputUpload, ".", part); }

int64_t InputPartOf(std::string_view slot) {
  const std::string_view input = kInputUpload;
  if (slot == input) return 0;
  if (!slot.starts_with(input) || slot.size() < input.size() + 2 || slot[input.size()] != '.') return -1;
  const std::string_view digits = slot.substr(input.size() + 1);
  // Canonical numbers only: "input.01" would be a second name for part 1.
  if (digits.size() > 6 || digits[0] == '0') return -1;
  int64_t part = 0;
  for (const char c : digits) {
    if (c < '0' || c > '9') return -1;
    part = 10 * part + (c - '0');
  }
  return part < kMaxInputParts ? part : -1;
}

std::string MeshPartArtifact(int64_t part) { return fmt::format("mesh-part-{:05d}.lqm", part); }

int64_t MeshPartOf(std::string_view name) {
  constexpr std::string_view kPrefix = "mesh-part-", kSuffix = ".lqm";
  if (!name.starts_with(kPrefix) || !name.ends_with(kSuffix)) return -1;
  const std::string_view digits = name.substr(kPrefix.size(), name.size() - kPrefix.size() - kSuffix.size());
  int64_t part = 0;
  if (digits.size() < 5 || digits.size() > 12) return -1;
  for (const char c : digits) {
    if (c < '0' || c > '9') return -1;
    part = 10 * part + (c - '0');
  }
  return MeshPartArtifact(part) == name ? part : -1;
}

std::vector<std::string_view> InputParts(const Uploads& uploads) {
  std::vector<std::string_view> parts;
  for (int64_t part = 0; part < kMaxInputParts; ++part) {
    auto it = uploads.find(InputPartSlot(part));
    if (it == uploads.end()) break;
    parts.push_back(it->second);
  }
  return parts;
}

std::optional<uint64_t> DeclaredPoints(std::string_view head) {
  auto claim = io::ReadDracoClaim(head);
  if (!claim.ok()) return std::nullopt;
  return claim->points;
}

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

const JobKind* KindFor(const std::map<std::string, const JobKind*>& overrides, const std::string& method) {
  if (auto it = overrides.find(method); it != overrides.end()) return it->second;
  const MethodEntry* m = FindMethod(method);
  return m ? m->kind : nullptr;
}

absl::StatusOr<std::unique_ptr<BlobReader>> OpenJobResult(const JobTable& table, BlobStore& blobs,
                                                          const std::string& id, const std::string& name) {
  auto r = table.Get(id);
  if (!r.ok()) return r.status();
  // A running job's published parts are there already (each stored whole before it is listed).
  const bool published = r->state == JobState::kRunning && MeshPartOf(name) >= 0;
  if (r->state != JobState::kSucceeded && !published) {
    return absl::FailedPreconditionError(core::StrCat("job ", id, " is ", JobStateName(r->state),
                                                      "; results exist only for succeeded jobs (and the mesh parts "
                                                      "of a running one)"));
  }
  if (!name.empty() && !IsArtifactNameForm(name)) return absl::InvalidArgumentError(kNotAnArtifactName);
  const std::string artifact = name.empty() && !r->results.empty() ? r->results.front() : name;
  if (std::find(r->results.begin(), r->results.end(), artifact) == r->results.end()) {
    std::string names;
    for (const auto& n : r->results) core::StrAppend(&names, names.empty() ? "" : ", ", n);
    return absl::NotFoundError(core::StrCat("job ", id, " has no result '", artifact, "'; it has: ", names));
  }
  return blobs.Open(id, artifact);
}

JobService::JobService(JobServiceOptions options) : options_(std::move(options)), runner_(RunnerName(options_.name)) {
  if (options_.max_job_memory < 0) options_.max_job_memory = PhysicalMemoryBytes() / 4 * 3;
}

absl::StatusOr<std::unique_ptr<JobService>> JobService::Open(const JobServiceOptions& options) {
  if (options.data_dir.empty()) return absl::InvalidArgumentError("a data directory is required");
  if (options.workers < 1 || options.max_queue < 1 || options.max_renders < 1) {
    return absl::InvalidArgumentError("workers, max_queue and max_renders must be at least 1");
  }
  if (options.lease < std::chrono::milliseconds(100) || options.poll < std::chrono::milliseconds(1)) {
    return absl::InvalidArgumentError("the lease must be at least 100 ms and the poll interval at least 1 ms");
  }
  std::error_code ec;
  std::filesystem::create_directories(options.data_dir, ec);
  if (ec) {
    return absl::UnavailableError(core::StrCat("cannot create data directory ", options.data_dir, ": ", ec.message()));
  }
  std::unique_ptr<JobService> service(new JobService(options));
  JobService& s = *service;
  if (options.blobs != nullptr) {
    s.blobs_ = options.blobs;
  } else {
    auto blobs = LocalDirBlobStore::Open((std::filesystem::path(options.data_dir) / "jobs").string());
    if (!blobs.ok()) return blobs.status();
    s.blobs_ = *std::move(blobs);
  }
  if (options.store != nullptr) {
    s.store_ = options.store;
  } else {
    auto store =
        SqliteJobStore::Open((std::filesystem::path(options.data_dir) / "jobs.db").string(), RegistrySpecTables());
    if (!store.ok()) return store.status();
    s.store_ = *std::move(store);
  }
  // Large temporary files (a tiled build's points) stay beside the data, not in a temporary
  // directory that may be memory; those of a crashed run go now.
  s.scratch_dir_ = (std::filesystem::path(options.data_dir) / "scratch").string();
  std::filesystem::create_directories(s.scratch_dir_, ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot create ", s.scratch_dir_, ": ", ec.message()));

  const JobServiceOptions& o = s.options_;
  s.decoded_ = std::make_unique<DecodedInputs>(o.max_points);
  s.table_ = std::make_unique<JobTable>(s.store_, *s.decoded_);
  s.pictures_ = std::make_unique<JobPictures>(*s.table_, *s.blobs_, o.max_renders, o.max_render_bytes);
  s.retention_ = std::make_unique<JobRetention>(RetentionLimits{o.retain, o.max_store_bytes, o.sweep_interval},
                                                *s.table_, *s.store_, *s.blobs_);
  const auto wake_workers = [&s] { s.runner_threads_->WakeWorkers(); };
  s.admission_ = std::make_unique<JobAdmission>(o, *s.table_, *s.decoded_, *s.retention_, *s.pictures_, *s.store_,
                                                *s.blobs_, wake_workers);
  s.replication_ = std::make_unique<JobReplication>(o, s.runner_, *s.table_, *s.store_, wake_workers);
  s.runner_threads_ = std::make_unique<JobRunner>(
      o, s.runner_, s.scratch_dir_,
      JobRunner::Parts{*s.table_, *s.decoded_, *s.admission_, *s.pictures_, *s.store_, *s.blobs_});

  // In a store of its own every running job was this service's before it stopped; in a shared
  // one only those whose lease lapsed are known to be orphans (the sync thread goes on looking).
  const bool shared = s.store_->shared();
  if (shared) LSQSURF_RETURN_IF_ERROR(s.replication_->CheckBlobsShared(*s.blobs_));
  LSQSURF_RETURN_IF_ERROR(s.replication_->RecoverLapsed(!shared));
  LSQSURF_RETURN_IF_ERROR(s.replication_->LoadAll());
  if (!shared) s.retention_->RemoveOrphanedBlobs();
  auto swept = pu::SweepAbandonedScratch(s.scratch_dir_);
  if (!swept.ok()) return swept.status();
  if (*swept > 0) spdlog::info("removed the scratch files of {} runs that ended in a crash", *swept);
  const auto [on_record, queued] = s.table_->Locked([](const JobEntries& jobs) {
    int waiting = 0;
    for (const auto& [id, e] : jobs) waiting += e->record.state == JobState::kQueued && !IsChildJob(e->record);
    return std::pair{jobs.size(), waiting};
  });
  const int64_t job_memory = o.max_job_memory;
  spdlog::info("job service {}: {} jobs on record, {} queued, {} workers, {}, data in {}{}", s.runner_, on_record,
               queued, o.workers,
               job_memory > 0 ? core::StrCat("at most ", MiB(job_memory), " MiB a job") : "no memory limit per job",
               o.data_dir, shared ? ", store shared with other servers" : "");
  s.runner_threads_->Start();
  s.replication_->Start();
  s.retention_->Start();
  return service;
}

JobService::~JobService() { Shutdown(); }

absl::StatusOr<JobRecord> JobService::Submit(const JobSpec& spec, Uploads uploads, const Submitter& submitter) {
  return admission_->Submit(spec, std::move(uploads), submitter);
}

absl::StatusOr<JobRecord> JobService::Get(const std::string& id) const { return table_->Get(id); }

absl::StatusOr<JobRecord> JobService::GetFor(const Submitter& who, const std::string& id) const {
  auto record = Get(id);
  if (record.ok() && !MayView(who, *record)) return NoSuchJob(id);
  return record;
}

std::vector<JobRecord> JobService::List() const { return table_->List(); }

absl::StatusOr<JobRecord> JobService::Cancel(const std::string& id) { return table_->Cancel(id); }

absl::StatusOr<std::unique_ptr<BlobReader>> JobService::OpenResult(const std::string& id,
                                                                   const std::string& name) const {
  return OpenJobResult(*table_, *blobs_, id, name);
}

absl::StatusOr<RenderedPicture> JobService::Render(const Submitter& who, const std::string& id, const std::string& name,
                                                   const core::ParamSet& view, const core::JobContext* ctx) {
  auto record = GetFor(who, id);
  if (!record.ok()) return record.status();
  return pictures_->Render(who.owner, *record, name, view, ctx);
}

bool JobService::CanRender() { return pictures_->CanRender(); }

uint64_t JobService::WaitForAnyChange(uint64_t seen, std::chrono::milliseconds timeout) const {
  return table_->WaitForAnyChange(seen, timeout);
}

absl::StatusOr<JobRecord> JobService::WaitForChange(const std::string& id, uint64_t seen_version,
                                                    std::chrono::milliseconds timeout) const {
  return table_->WaitForChange(id, seen_version, timeout);
}

bool JobService::StoreReachable() const { return replication_->StoreReachable(); }

bool JobService::shutting_down() const { return table_->shutting_down(); }

void JobService::Shutdown() {
  std::lock_guard lock(shutdown_mutex_);
  if (table_ == nullptr) return;  // Open failed before the parts were made.
  table_->BeginShutdown();
  retention_->Stop();
  runner_threads_->Stop();
  // The leases are renewed until the interrupted jobs are back in the queue.
  replication_->Stop();
}

}  // namespace lsqsurf::jobs
