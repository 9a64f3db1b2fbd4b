#include "worker/jobs/job_retention.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <set>
#include <tuple>
#include <vector>

#include "worker/core/status.h"
#include "worker/jobs/job_service_internal.h"

namespace lsqsurf::jobs {

absl::Status JobRetention::Delete(const std::string& id) {
  LSQSURF_RETURN_IF_ERROR(store_.Remove(id));
  table_.Locked([&](const JobEntries& jobs) {
    std::vector<std::string> gone = {id};
    for (const auto& [child, e] : jobs) {
      if (e->record.parent == id && !e->held) gone.push_back(child);  // Removed with it (JobStore::Remove).
    }
    for (const std::string& g : gone) {
      if (jobs.contains(g)) table_.EraseLocked(g);
    }
    return 0;
  });
  if (absl::Status s = blobs_.RemoveJob(id); !s.ok()) spdlog::error("[job {}] {}", id, s.ToString());
  table_.NotifyChanged();
  spdlog::info("[job {}] deleted", id);
  return absl::OkStatus();
}

void JobRetention::RemoveOrphanedBlobs() {
  const std::set<std::string> known = table_.Locked([](const JobEntries& jobs) {
    std::set<std::string> ids;
    for (const auto& [id, e] : jobs) ids.insert(id);
    return ids;
  });
  auto removed = blobs_.RemoveOrphans([&](const std::string& id) { return known.count(id) > 0; });
  if (!removed.ok()) {
    if (removed.status().code() != absl::StatusCode::kUnimplemented) {
      spdlog::warn("orphaned files not removed: {}", removed.status().ToString());
    }
  } else if (*removed > 0) {
    spdlog::info("removed the files of {} jobs that were never stored or whose deletion was cut short", *removed);
  }
}

int64_t JobRetention::RecordedBytes() const {
  return table_.Locked([](const JobEntries& jobs) {
    int64_t total = 0;
    for (const auto& [id, e] : jobs) total += e->record.stored_bytes;
    return total;
  });
}

int JobRetention::SweepFinished(int64_t now_ms, int64_t room) {
  struct Finished {
    int64_t ended_ms, seq, bytes;
    std::string id;
  };
  std::vector<Finished> finished;
  int64_t total = 0;
  table_.Locked([&](const JobEntries& jobs) {
    for (const auto& [id, e] : jobs) {
      total += e->record.stored_bytes;
      // A tile's job goes with its build.
      if (IsTerminal(e->record.state) && !IsChildJob(e->record)) {
        finished.push_back({e->record.updated_ms, e->record.seq, e->record.stored_bytes, id});
      }
    }
    return 0;
  });
  std::sort(finished.begin(), finished.end(), [](const Finished& a, const Finished& b) {
    return std::tie(a.ended_ms, a.seq) < std::tie(b.ended_ms, b.seq);  // Within a millisecond, store order.
  });
  const int64_t retain_ms = std::chrono::duration_cast<std::chrono::milliseconds>(limits_.retain).count();
  int removed = 0;
  for (const Finished& f : finished) {
    const bool expired = retain_ms > 0 && now_ms - f.ended_ms > retain_ms;
    const bool over = limits_.max_store_bytes > 0 && total + room > limits_.max_store_bytes;
    if (!expired && !over) break;  // Oldest first: the rest are newer.
    // Another server sharing the store may have deleted it already.
    if (absl::Status s = Delete(f.id); !s.ok() && s.code() != absl::StatusCode::kNotFound) {
      spdlog::warn("[job {}] not deleted by retention: {}", f.id, s.ToString());
      continue;
    }
    total -= f.bytes;
    ++removed;
    spdlog::info("[job {}] deleted by retention ({})", f.id,
                 expired ? "older than --retain-days" : "store over --max-store-gib");
  }
  return removed;
}

void JobRetention::Start() {
  if (limits_.retain.count() <= 0 && limits_.max_store_bytes <= 0) return;
  thread_ = std::thread([this] {
    std::unique_lock lock(mutex_);
    while (!wake_.wait_for(lock, limits_.sweep_interval, [this] { return stop_; })) {
      lock.unlock();
      SweepFinished(NowMs());
      lock.lock();
    }
  });
}

void JobRetention::Stop() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

}  // namespace lsqsurf::jobs
