#include <spdlog/spdlog.h>

#include <algorithm>
#include <set>
#include <tuple>

#include "worker/jobs/job_service.h"
#include "worker/jobs/job_service_internal.h"

namespace lsqsurf::jobs {

void JobService::RemoveOrphanedBlobs() {
  std::set<std::string> known;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, e] : jobs_) known.insert(id);
  }
  auto removed = blobs_->RemoveOrphans([&](const std::string& id) { return known.count(id) > 0; });
  if (!removed.ok()) {
    if (removed.status().code() != absl::StatusCode::kUnimplemented) {
      spdlog::warn("orphaned files not removed: {}", removed.status().ToString());
    }
  } else if (*removed > 0) {
    spdlog::info("removed the files of {} jobs that were never stored or whose deletion was cut short", *removed);
  }
}

int64_t JobService::StoredBytes() const {
  std::lock_guard lock(mutex_);
  int64_t total = 0;
  for (const auto& [id, e] : jobs_) total += e->record.stored_bytes;
  for (const auto& [owner, usage] : pending_) total += usage.stored_bytes;
  return total;
}

int JobService::SweepFinished(int64_t now_ms, int64_t room) {
  struct Finished {
    int64_t ended_ms, seq, bytes;
    std::string id;
  };
  std::vector<Finished> finished;
  int64_t total = 0;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, e] : jobs_) {
      total += e->record.stored_bytes;
      if (IsTerminal(e->record.state)) {
        finished.push_back({e->record.updated_ms, e->record.seq, e->record.stored_bytes, id});
      }
    }
  }
  std::sort(finished.begin(), finished.end(), [](const Finished& a, const Finished& b) {
    return std::tie(a.ended_ms, a.seq) < std::tie(b.ended_ms, b.seq);  // Within a millisecond, store order.
  });
  const int64_t retain_ms = std::chrono::duration_cast<std::chrono::milliseconds>(options_.retain).count();
  int removed = 0;
  for (const Finished& f : finished) {
    const bool expired = retain_ms > 0 && now_ms - f.ended_ms > retain_ms;
    const bool over = options_.max_store_bytes > 0 && total + room > options_.max_store_bytes;
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

}  // namespace lsqsurf::jobs
