// server/http_front.h — the HTTP listener under the job page: GNU libmicrohttpd on event loops,
// with every resource a client can hold bounded before it is held.
//
// Why not a thread per connection: a client that sends its request one byte at a time, or not at
// all, would hold a thread for as long as it liked. Here connections wait in epoll and cost a
// file descriptor and their share of `connection_memory_bytes`; a request reaches the handler
// only once its whole head has arrived, within `head_seconds` of the connection's start (or of
// the previous answer on a kept-alive connection), however slowly or quickly it trickles in.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"

namespace lsqsurf::server {

// What one client, and all of them together, may hold of the HTTP port. Defaults suit a page
// watched by a handful of browsers; each has a flag (lsqsurfd --help, README's Security section).
struct HttpLimits {
  // The request line and headers of one request must fit in this (with the connection's own
  // bookkeeping); a longer head is answered 431 and the connection closed.
  size_t connection_memory_bytes = 32 << 10;
  // Connections open at once, in all and from one address; past them a new one is closed at once.
  unsigned max_connections = 512;
  unsigned max_connections_per_peer = 128;
  // From a connection's start, or the end of its previous answer, to the end of the next
  // request's head; not reset by bytes that trickle in.
  unsigned head_seconds = 10;
  // No byte either way for this long closes a connection (an answer the client stopped reading).
  unsigned idle_seconds = 30;
  // Requests on one kept-alive connection; the last answer says `Connection: close`.
  unsigned max_requests_per_connection = 100;
  // Connections the kernel holds before they are accepted.
  int listen_backlog = 64;
  // Event loops; a handler runs on its loop's thread.
  unsigned threads = 4;
};

struct HttpRequest {
  std::string method;                          // GET, HEAD, ...
  std::string path;                            // Percent-decoded, without the query.
  std::map<std::string, std::string> query;    // Decoded arguments.
  std::map<std::string, std::string> headers;  // Names in lower case.
  std::string header(const std::string& lower_name) const {
    auto found = headers.find(lower_name);
    return found == headers.end() ? "" : found->second;
  }
};

struct HttpAnswer {
  int status = 200;
  std::vector<std::pair<std::string, std::string>> headers;
  std::string body;
  // When set, the body is pulled from here instead, as the client takes it: it fills up to the
  // size given and returns the bytes written, 0 at the end, or -1 to cut the transfer. Dropped
  // (with whatever it holds) when the transfer ends or the client goes.
  std::function<int64_t(char*, size_t)> stream;
  int64_t stream_size = -1;  // The body's length when streamed; -1: unknown (chunked).
};

using HttpHandler = std::function<HttpAnswer(const HttpRequest&)>;

struct HttpFrontOptions {
  // HOST:PORT (HOST may be a name, an IPv4 address or [IPv6]); port 0 picks a free one.
  std::string listen = "127.0.0.1:0";
  // PEM files to serve HTTPS with; both empty: plain HTTP.
  std::string tls_cert_path;
  std::string tls_key_path;
  // Host names (besides loopback names and IP addresses) that requests may name in `Host`. Any
  // other name is refused (421) before the handler runs: a web page that rebinds its own name to
  // this address cannot read the API through the visitor's browser.
  std::vector<std::string> host_names;
  HttpLimits limits;
};

// `text` as a JSON string, quotes included (control bytes as \u00XX).
std::string JsonQuoted(std::string_view text);

// Whether `host` (a Host header's value, with or without a port) is one the front answers to:
// an IP address literal, `localhost`, or one of `names` (case-insensitive).
bool HostAllowed(const std::string& host, const std::vector<std::string>& names);

class HttpFront {
 public:
  // Errors: kInvalidArgument (a malformed address), kUnavailable (cannot bind, no TLS support in
  // the library, or the TLS files do not load).
  static absl::StatusOr<std::unique_ptr<HttpFront>> Start(const HttpFrontOptions& options, HttpHandler handler);
  ~HttpFront();  // Stops serving; answers under way are cut.
  HttpFront(const HttpFront&) = delete;
  HttpFront& operator=(const HttpFront&) = delete;

  std::string scheme() const;  // "http" or "https".
  int port() const;
  // Connections open now, those being closed for want of room included; a connection whose client
  // has gone counts until the library has noticed.
  size_t open_connections() const;

  struct State;  // Defined in http_front.cc, where the library's callbacks reach it.

 private:
  explicit HttpFront(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

}  // namespace lsqsurf::server
