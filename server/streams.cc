#include "server/streams.h"

#include <grpcpp/server_context.h>
#include <spdlog/spdlog.h>

#include <cmath>

#include "worker/core/strings.h"

namespace lsqsurf::server {
namespace {

int64_t SteadyMs(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(t.time_since_epoch()).count();
}

// The lsqsurfd option that sets each kind's bound, for the refusal.
const char* OptionOf(StreamKind kind) {
  switch (kind) {
    case StreamKind::kUpload: return "--max-uploads";
    case StreamKind::kDownload: return "--max-downloads";
    case StreamKind::kWatch: return "--max-watches";
    case StreamKind::kReflection: return "--max-reflection-streams";
  }
  return "";
}

}  // namespace

const char* StreamKindName(StreamKind kind) {
  switch (kind) {
    case StreamKind::kUpload: return "uploads";
    case StreamKind::kDownload: return "downloads";
    case StreamKind::kWatch: return "watches";
    case StreamKind::kReflection: return "reflection streams";
  }
  return "streams";
}

struct StreamGuard::Entry {
  StreamKind kind;
  std::string owner;
  grpc::CallbackServerContext* context;
  std::atomic<int64_t> last_ms;  // steady_clock milliseconds.
  bool cancelled = false;        // By the sweeper (mutex_).
  std::atomic<bool> busy{false};
};

StreamGuard::Ticket::~Ticket() { guard_.Release(id_); }

void StreamGuard::Ticket::Touch() { entry_->last_ms.store(SteadyMs(std::chrono::steady_clock::now())); }

void StreamGuard::Ticket::SetBusy(bool busy) {
  Touch();
  entry_->busy.store(busy);
}

StreamGuard::StreamGuard(StreamLimits limits) : limits_(limits) {
  for (StreamKind kind : {StreamKind::kUpload, StreamKind::kDownload, StreamKind::kWatch, StreamKind::kReflection}) {
    slots_.emplace(kind, core::FairSlots(Limit(kind), limits_.per_user_share));
  }
  sweeper_ = std::thread([this] {
    std::unique_lock lock(stop_mutex_);
    while (!stop_wake_.wait_for(lock, std::chrono::seconds(1), [this] { return stopping_; })) {
      lock.unlock();
      CancelIdle(std::chrono::steady_clock::now());
      lock.lock();
    }
  });
}

StreamGuard::~StreamGuard() {
  {
    std::lock_guard lock(stop_mutex_);
    stopping_ = true;
  }
  stop_wake_.notify_all();
  sweeper_.join();
}

int StreamGuard::Limit(StreamKind kind) const {
  switch (kind) {
    case StreamKind::kUpload: return limits_.max_uploads;
    case StreamKind::kDownload: return limits_.max_downloads;
    case StreamKind::kWatch: return limits_.max_watches;
    case StreamKind::kReflection: return limits_.max_reflection;
  }
  return 0;
}

std::string PeerHolder(const std::string& peer) {
  // "ipv4:127.0.0.1:54321", "ipv6:[::1]:54321": the address without its port.
  const size_t colon = peer.rfind(':');
  const size_t kind = peer.find(':');
  return core::StrCat("peer ", colon != std::string::npos && colon != kind ? peer.substr(0, colon) : peer);
}

absl::StatusOr<std::unique_ptr<StreamGuard::Ticket>> StreamGuard::Admit(StreamKind kind, const std::string& user,
                                                                        grpc::CallbackServerContext* context) {
  // A client without a name is held to a user's share per address, so that one tokenless client
  // cannot hold every stream (a space keeps "peer ..." apart from every user name).
  const std::string owner = user.empty() && context != nullptr ? PeerHolder(context->peer()) : user;
  std::lock_guard lock(mutex_);
  core::FairSlots& slots = slots_.at(kind);
  switch (slots.TryTake(owner)) {
    case core::FairSlots::Refusal::kFull:
      return absl::ResourceExhaustedError(core::StrCat("this server has ", slots.limit(), " ", StreamKindName(kind),
                                                       " open, its limit (lsqsurfd ", OptionOf(kind),
                                                       "); try again shortly"));
    case core::FairSlots::Refusal::kOwnerFull:
      return absl::ResourceExhaustedError(core::StrCat("you have ", slots.owner_share(), " ", StreamKindName(kind),
                                                       " open, your share of this server's ", slots.limit(),
                                                       "; finish one first"));
    case core::FairSlots::Refusal::kNone: break;
  }
  const uint64_t id = next_id_++;
  auto entry = std::make_unique<Entry>();
  entry->kind = kind;
  entry->owner = owner;
  entry->context = context;
  entry->last_ms = SteadyMs(std::chrono::steady_clock::now());
  Entry* raw = entry.get();
  entries_.emplace(id, std::move(entry));
  return std::unique_ptr<Ticket>(new Ticket(*this, id, raw));
}

void StreamGuard::Release(uint64_t id) {
  std::lock_guard lock(mutex_);
  auto it = entries_.find(id);
  if (it == entries_.end()) return;
  const Entry& e = *it->second;
  slots_.at(e.kind).Release(e.owner);
  entries_.erase(it);
}

int StreamGuard::Open(StreamKind kind) const {
  std::lock_guard lock(mutex_);
  return slots_.at(kind).held();
}

int StreamGuard::CancelIdle(std::chrono::steady_clock::time_point now) {
  const int64_t cutoff = SteadyMs(now) - limits_.idle.count();
  std::lock_guard lock(mutex_);
  std::vector<Entry*> idle;
  for (const auto& [id, e] : entries_) {
    if (e->kind != StreamKind::kWatch && !e->cancelled && !e->busy.load() && e->last_ms.load() < cutoff) {
      idle.push_back(e.get());
    }
  }
  // A cancellation may release its entry on this thread (the mutex is recursive), so the loop
  // runs over the list taken above; each entry is touched before its own cancellation only.
  for (Entry* e : idle) {
    e->cancelled = true;
    spdlog::info("a stream of {} idle for over {} s is cancelled", e->owner.empty() ? "an unnamed client" : e->owner,
                 limits_.idle.count() / 1000);
    e->context->TryCancel();
  }
  return static_cast<int>(idle.size());
}

absl::Status SpoolLedger::Reserve(const std::string& owner, int64_t bytes, const Room& room) {
  std::lock_guard lock(mutex_);
  if (room.disk_free >= 0 && room.disk_free - bytes < room.min_free) {
    return absl::ResourceExhaustedError(core::StrCat("the server's disk is nearly full (", room.disk_free >> 20,
                                                     " MiB free, ", room.min_free >> 20,
                                                     " MiB kept for running jobs); the upload stops here: try again "
                                                     "later"));
  }
  int64_t& mine = by_owner_[owner];
  if (room.quota > 0 && room.stored + mine + bytes > room.quota) {
    const int64_t in_flight = mine;
    if (mine == 0) by_owner_.erase(owner);
    return absl::ResourceExhaustedError(core::StrCat(
        "this upload would pass your quota of ", room.quota, " bytes: your jobs keep ", room.stored,
        " and your uploads in progress hold ", in_flight, "; delete finished jobs or wait for your uploads"));
  }
  mine += bytes;
  return absl::OkStatus();
}

void SpoolLedger::Release(const std::string& owner, int64_t bytes) {
  std::lock_guard lock(mutex_);
  auto it = by_owner_.find(owner);
  if (it == by_owner_.end()) return;
  it->second -= bytes;
  if (it->second <= 0) by_owner_.erase(it);
}

int64_t SpoolLedger::InFlight(const std::string& owner) const {
  std::lock_guard lock(mutex_);
  auto it = by_owner_.find(owner);
  return it == by_owner_.end() ? 0 : it->second;
}

}  // namespace lsqsurf::server
