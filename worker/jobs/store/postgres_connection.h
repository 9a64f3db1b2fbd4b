// worker/jobs/store/postgres_connection.h — a small pool of libpq connections and a query helper.
//
// libpq's own C API is used directly: its errors become absl::Status values like the rest of
// the service, and LISTEN needs the raw socket. A connection is used by one thread at a time;
// the pool hands them out and reconnects one that broke.
#pragma once

#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

struct pg_conn;
struct pg_result;

namespace lsqsurf::jobs::pg {

// A query's result rows, each column as text (or raw bytes where binary results were asked for).
struct Rows {
  std::vector<std::vector<std::string>> rows;
  int64_t affected = 0;  // Rows an INSERT, UPDATE or DELETE changed.
};

// One parameter: text, or raw bytes sent in binary form (for bytea columns).
struct Param {
  std::string_view value;
  bool binary = false;
  Param(std::string_view v) : value(v) {}    // NOLINT: text parameters read naturally.
  Param(const std::string& v) : value(v) {}  // NOLINT
  Param(const char* v) : value(v) {}         // NOLINT
  static Param Bytes(std::string_view v) {
    Param p(v);
    p.binary = true;
    return p;
  }
};

// Runs one statement on `conn`. Errors: kAlreadyExists (a unique key), kAborted (a
// serialization failure or deadlock: try again), kUnavailable (anything else, with the server's
// message).
absl::StatusOr<Rows> Exec(pg_conn* conn, std::string_view sql, const std::vector<Param>& params = {},
                          bool binary_results = false);

// Opens a connection. Errors: kUnavailable with libpq's reason (the password never appears).
absl::StatusOr<pg_conn*> Connect(const std::string& url);
void Close(pg_conn* conn);

class Pool {
 public:
  // Connects once to check the URL; up to `size` connections are opened as needed.
  static absl::StatusOr<std::shared_ptr<Pool>> Open(std::string url, int size);
  ~Pool();

  // A connection for one thread until it goes out of scope.
  class Handle {
   public:
    Handle(Pool* pool, pg_conn* conn) : pool_(pool), conn_(conn) {}
    Handle(Handle&& other) noexcept : pool_(other.pool_), conn_(other.conn_) { other.conn_ = nullptr; }
    Handle(const Handle&) = delete;
    Handle& operator=(const Handle&) = delete;
    ~Handle();
    pg_conn* get() const { return conn_; }

   private:
    Pool* pool_;
    pg_conn* conn_;
  };
  // Waits for a free connection; reconnects one that broke. Errors: kUnavailable.
  absl::StatusOr<Handle> Acquire();
  // Runs one statement on a pooled connection.
  absl::StatusOr<Rows> Exec(std::string_view sql, const std::vector<Param>& params = {}, bool binary_results = false);
  // Runs `body` inside BEGIN ... COMMIT on one connection (ROLLBACK when it fails).
  absl::Status Transaction(const std::function<absl::Status(pg_conn*)>& body);
  const std::string& url() const { return url_; }

 private:
  Pool(std::string url, int size) : url_(std::move(url)), size_(size) {}
  void Release(pg_conn* conn);
  std::string url_;
  int size_;
  std::mutex mutex_;
  std::condition_variable released_;
  std::vector<pg_conn*> idle_;
  int open_ = 0;  // Connections made and not closed (idle or handed out).
};

// The URL with any password replaced by "***", for logs and messages.
std::string Redacted(const std::string& url);

}  // namespace lsqsurf::jobs::pg
