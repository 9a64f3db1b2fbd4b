#include "worker/jobs/job_replication.h"

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <random>
#include <set>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/jobs/job_service_internal.h"

namespace lsqsurf::jobs {
namespace {

// Where the witness of a shared blob store lives: a folder no job id can name (ids are hex).
constexpr char kWitnessFolder[] = "shared-store-witness";
constexpr char kWitnessSetting[] = "blob_store_witness";

}  // namespace

void RecoverStoppedRun(JobRecord& r, int max_attempts) {
  if (r.cancel_requested) {
    r.state = JobState::kCancelled;
    r.error = "cancelled by request (its server stopped while it ran)";
  } else if (r.attempts - r.interruptions >= max_attempts && IsChildJob(r)) {
    // A tile's child job: its build reports this, naming the tile (DecodeTileError).
    r.state = JobState::kFailed;
    r.error = core::StrCat("the server making it stopped on each of its ", r.attempts - r.interruptions,
                           " attempts (out of memory or a crash); lower tile_points or give the servers more memory");
  } else if (r.attempts - r.interruptions >= max_attempts) {
    r.state = JobState::kFailed;
    r.error = core::StrCat("the server stopped while this job was running, ", r.attempts - r.interruptions,
                           " times; giving up (the input may crash the engine)");
  } else {
    r.state = JobState::kQueued;
  }
  r.stage.clear();
  r.progress = 0;
  r.results.clear();  // Parts a run published (MeshPartArtifact); the next run publishes them again.
  r.cancel_requested = false;
  r.updated_ms = NowMs();
}

absl::Status JobReplication::CheckBlobsShared(BlobStore& blobs) {
  std::random_device random;
  const std::string mine = fmt::format("witness-{:08x}{:08x}", random(), random());
  // Written before it is named, so that whoever reads the name can read the blob.
  LSQSURF_RETURN_IF_ERROR(blobs.Put(kWitnessFolder, mine, runner_));
  auto named = store_.Agree(kWitnessSetting, mine);
  if (named.ok() && *named == mine) return absl::OkStatus();  // This server is the first.
  (void)blobs.Remove(kWitnessFolder, mine);
  if (!named.ok()) return named.status();
  auto seen = blobs.Read(kWitnessFolder, *named);
  if (seen.ok()) return absl::OkStatus();
  if (!absl::IsNotFound(seen.status())) return seen.status();
  return absl::FailedPreconditionError(core::StrCat(
      "this server's blob store does not hold the blob ", kWitnessFolder, "/", *named,
      " that the servers sharing its job store left there: its --blob-dir is not the one they share. Give every "
      "server the same shared volume, or no --blob-dir at all (the database then keeps the bytes). If the shared "
      "blob store was replaced on purpose, run `DELETE FROM settings WHERE key = '",
      kWitnessSetting, "'` on the database first"));
}

absl::Status JobReplication::LoadAll() {
  auto all = store_.ChangesSince(0);
  if (!all.ok()) return all.status();
  table_.Locked([&](const JobEntries&) {
    for (JobRecord& r : all->changed) table_.AdoptLocked(std::move(r));
    return 0;
  });
  synced_seq_ = all->seq;
  return absl::OkStatus();
}

absl::Status JobReplication::RecoverLapsed(bool every_running) {
  auto recovered =
      store_.RecoverLapsed(every_running, [this](JobRecord& r) { RecoverStoppedRun(r, options_.max_attempts); });
  // A full disk must not keep the server from starting (to serve what it stored, and let jobs be
  // deleted): the interrupted jobs stay as stored and are recovered at a start with room.
  if (absl::IsResourceExhausted(recovered.status())) {
    spdlog::error("cannot queue interrupted jobs again: {}; they resume at a start with room",
                  recovered.status().ToString());
    return absl::OkStatus();
  }
  if (!recovered.ok()) return recovered.status();
  for (const JobRecord& r : *recovered) {
    spdlog::warn("[job {}] its server ({}) stopped while it ran: {}", r.id, r.runner,
                 r.state == JobState::kQueued ? "queued again" : r.error);
  }
  return absl::OkStatus();
}

void JobReplication::SyncChanges() {
  auto changes = store_.ChangesSince(synced_seq_);
  // Logged when the store goes away and when it comes back, not at every poll.
  if (store_reachable_.exchange(changes.ok()) != changes.ok()) {
    if (changes.ok()) {
      spdlog::info("the job store answers again");
    } else {
      spdlog::warn("cannot reach the job store: {}", changes.status().ToString());
    }
  }
  if (!changes.ok()) return;
  const bool queued = table_.Locked([&](JobEntries& jobs) {
    bool any_queued = false;
    for (JobRecord& r : changes->changed) {
      const bool cancel = r.cancel_requested;
      // Queued again, someone else's, or ended while this run goes on: changes made by others
      // since this server claimed it (not this run's own writes, nor older states arriving late).
      auto known = jobs.find(r.id);
      const bool newer = known == jobs.end() || r.seq > known->second->record.seq;
      const bool ended_elsewhere =
          r.state != JobState::kRunning && known != jobs.end() && known->second->record.state == JobState::kRunning;
      const bool taken = newer && (r.runner != runner_ || r.state == JobState::kQueued || ended_elsewhere);
      const int64_t seq = r.seq;
      std::shared_ptr<JobEntry> entry = table_.AdoptLocked(std::move(r));
      if (entry->held) {
        // The runner learns of a cancellation asked of another service, and of a lease that
        // lapsed while it could not renew (the job went back to the queue or to another).
        // While its own write is under way, that write may be what arrived: the write decides.
        if (cancel) entry->cancel_requested = true;
        if (taken && entry->writes_in_flight > 0) {
          entry->seq_seen_while_writing = std::max(entry->seq_seen_while_writing, seq);
        } else if (taken && !entry->interrupted) {
          JobTable::MarkLost(*entry, entry->record.id);
        }
      }
      any_queued = any_queued || entry->record.state == JobState::kQueued;
    }
    for (const std::string& id : changes->removed) {
      auto it = jobs.find(id);
      if (it == jobs.end()) continue;
      if (it->second->held) {
        // Its run ends by itself (its next write finds no lease); then the entry goes.
        it->second->removed_elsewhere = true;
        continue;
      }
      table_.EraseLocked(id);
    }
    return any_queued;
  });
  synced_seq_ = changes->seq;
  table_.NotifyChanged();
  if (queued) wake_workers_();
}

void JobReplication::RenewLeases() {
  const std::vector<std::string> running = table_.Locked([](const JobEntries& jobs) {
    std::vector<std::string> ids;
    for (const auto& [id, e] : jobs) {
      if (e->held && !e->lost) ids.push_back(id);
    }
    return ids;
  });
  auto held = store_.Renew(runner_, running, options_.lease);
  if (!held.ok()) {
    spdlog::warn("cannot renew the leases of the running jobs: {}", held.status().ToString());
    return;
  }
  table_.Locked([&](const JobEntries& jobs) {
    std::set<std::string> ids;
    for (const auto& [id, cancel] : *held) {
      ids.insert(id);
      auto it = jobs.find(id);
      if (cancel && it != jobs.end()) it->second->cancel_requested = true;
    }
    for (const std::string& id : running) {
      auto it = jobs.find(id);
      // Held here but not in the store any more: taken over, or finished a moment ago (its
      // final write may be under way; if it was taken, that write is refused).
      if (it != jobs.end() && it->second->held && it->second->writes_in_flight == 0 &&
          it->second->record.state == JobState::kRunning && !ids.contains(id))
        it->second->lost = true;
    }
    return 0;
  });
}

void JobReplication::Start() {
  if (store_.shared()) thread_ = std::thread([this] { SyncLoop(); });
}

void JobReplication::Stop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
}

void JobReplication::SyncLoop() {
  using Clock = std::chrono::steady_clock;
  Clock::time_point next_renewal = Clock::now(), next_recovery = Clock::now();
  while (!stop_) {
    store_.WaitForOthers(options_.poll);
    SyncChanges();
    const Clock::time_point now = Clock::now();
    if (now >= next_renewal) {
      RenewLeases();
      next_renewal = now + options_.lease / 4;
    }
    if (now >= next_recovery) {
      if (absl::Status s = RecoverLapsed(false); !s.ok()) spdlog::warn("cannot recover lapsed jobs: {}", s.ToString());
      next_recovery = now + options_.lease / 2;
    }
  }
}

}  // namespace lsqsurf::jobs
