// server/streams.h — what the open streams of every kind may hold: how many at once (in all and
// per user), and how long one may sit idle.
//
// Streaming calls run on gRPC's callback API, so an open stream costs no thread; what it costs is
// memory (the transport's buffers, a chunk in flight) and, for an upload, disk. Each stream is
// admitted here before it is served (a refusal is RESOURCE_EXHAUSTED with the option to change)
// and reports activity as it moves; one idle past its kind's limit is cancelled by a sweeper
// thread, and its client sees the stream end. Watches have no idle limit: waiting is what they
// are for.
#pragma once

#include <grpcpp/support/server_callback.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/statusor.h"
#include "worker/core/fair_slots.h"

namespace grpc {
class CallbackServerContext;
}

namespace lsqsurf::server {

enum class StreamKind { kUpload, kDownload, kWatch, kReflection };
// How an unnamed client's streams are counted: "peer ADDRESS" of a gRPC peer ("ipv4:HOST:PORT").
std::string PeerHolder(const std::string& peer);
const char* StreamKindName(StreamKind kind);

// The bounds, each a documented lsqsurfd option.
struct StreamLimits {
  int max_uploads = 64;     // SubmitJob streams open at once.
  int max_downloads = 64;   // FetchResult streams.
  int max_watches = 4096;   // WatchJob streams.
  int max_reflection = 64;  // Server reflection streams (open without a token).
  // A named user, or a client without a token at one address, holds at most this share of
  // each kind's streams (rounded up), so that no one holds all of them.
  double per_user_share = 0.5;
  // An upload that sends nothing, a download whose client reads nothing, or a reflection stream
  // that asks nothing for this long is cancelled.
  std::chrono::milliseconds idle{60'000};
};

class StreamGuard {
  struct Entry;

 public:
  // One admitted stream; Touch() on every move. Releases its place when destroyed (in the
  // reactor's OnDone, after which the context is gone).
  class Ticket {
   public:
    ~Ticket();
    Ticket(const Ticket&) = delete;
    Ticket& operator=(const Ticket&) = delete;
    void Touch();
    // While busy, the stream waits on the server, not on its client (a finished upload whose job
    // is being checked and stored): it is never idle, whatever its last move.
    void SetBusy(bool busy);

   private:
    friend class StreamGuard;
    Ticket(StreamGuard& guard, uint64_t id, Entry* entry) : guard_(guard), id_(id), entry_(entry) {}
    StreamGuard& guard_;
    uint64_t id_;
    Entry* entry_;
  };

  explicit StreamGuard(StreamLimits limits);
  ~StreamGuard();  // Stops the sweeper; every ticket must be gone.

  // A place for a stream of `kind` for `owner` (empty: unnamed, held to a share per peer address
  // of `context`, or only to the kind's total without one).
  // Errors: kResourceExhausted naming the bound.
  absl::StatusOr<std::unique_ptr<Ticket>> Admit(StreamKind kind, const std::string& owner,
                                                grpc::CallbackServerContext* context);
  int Open(StreamKind kind) const;  // Streams of that kind now.
  const StreamLimits& limits() const { return limits_; }
  // Cancels the streams idle past the limit as of `now` (the sweeper's work, every second).
  // Returns how many.
  int CancelIdle(std::chrono::steady_clock::time_point now);

 private:
  void Release(uint64_t id);
  int Limit(StreamKind kind) const;

  const StreamLimits limits_;
  // Recursive: a cancellation may run the stream's reactions, and so its release, on the sweeping
  // thread itself.
  mutable std::recursive_mutex mutex_;
  std::map<uint64_t, std::unique_ptr<Entry>> entries_;
  std::map<StreamKind, core::FairSlots> slots_;  // By kind.
  uint64_t next_id_ = 1;
  std::mutex stop_mutex_;
  std::condition_variable stop_wake_;
  bool stopping_ = false;
  std::thread sweeper_;
};

// The bytes of the uploads in progress, by user: a spool holds disk before its job exists, so
// each chunk is counted, before it is written, against the disk's reserve for running jobs and
// against its user's stored-bytes quota together with the user's other uploads.
class SpoolLedger {
 public:
  struct Room {
    int64_t disk_free = -1;  // Bytes free on the spool's disk; -1: unknown.
    int64_t min_free = 0;    // Bytes kept free for running jobs (--min-free-mib).
    int64_t quota = 0;       // The user's stored-bytes quota; 0: none.
    int64_t stored = 0;      // What the user's jobs keep now.
  };
  // Errors: kResourceExhausted, saying which bound.
  absl::Status Reserve(const std::string& owner, int64_t bytes, const Room& room);
  void Release(const std::string& owner, int64_t bytes);
  int64_t InFlight(const std::string& owner) const;

 private:
  mutable std::mutex mutex_;
  std::map<std::string, int64_t> by_owner_;
};

// A reactor that ends its call at once with `status` (a refusal before any stream work).
template <class Base>
class Refusal final : public Base {
 public:
  explicit Refusal(grpc::Status status) { this->Finish(std::move(status)); }
  void OnDone() override { delete this; }
};

}  // namespace lsqsurf::server
