#include "server/http_front.h"

#include <arpa/inet.h>
#include <microhttpd.h>
#include <netdb.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cctype>
#include <charconv>
#include <chrono>
#include <condition_variable>
#include <cstdarg>
#include <cstdio>
#include <fstream>
#include <mutex>
#include <set>
#include <sstream>
#include <thread>

#include "absl/status/status.h"
#include "spdlog/spdlog.h"
#include "worker/core/strings.h"

namespace lsqsurf::server {
namespace {

using core::StrCat;
using Clock = std::chrono::steady_clock;

// One accepted connection, as the sweeper sees it.
struct Connection {
  int fd = -1;
  // When its next request's head must have arrived; max() while a request is being answered.
  Clock::time_point head_deadline = Clock::time_point::max();
  unsigned requests = 0;
  bool last_request = false;  // The one being answered is its last (Connection: close).
  size_t body_bytes = 0;      // Of the request being read.
  bool cut = false;
};

std::string Lower(std::string text) {
  for (char& c : text) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return text;
}

bool IsIpLiteral(const std::string& host) {
  in_addr v4;
  in6_addr v6;
  return inet_pton(AF_INET, host.c_str(), &v4) == 1 || inet_pton(AF_INET6, host.c_str(), &v6) == 1;
}

// The host of "HOST", "HOST:PORT", "[V6]" or "[V6]:PORT", lower case, without a trailing dot.
std::string HostPart(const std::string& value) {
  std::string host = value;
  if (!host.empty() && host.front() == '[') {
    const size_t close = host.find(']');
    host = close == std::string::npos ? "" : host.substr(1, close - 1);
  } else if (const size_t colon = host.rfind(':'); colon != std::string::npos && host.find(':') == colon) {
    host = host.substr(0, colon);
  }
  if (!host.empty() && host.back() == '.') host.pop_back();
  return Lower(host);
}

struct ListenSocket {
  int fd = -1;
  int port = 0;
  bool ipv6 = false;
};

// Binds and listens on HOST:PORT itself, so that the backlog and the address family are ours.
absl::StatusOr<ListenSocket> Listen(const std::string& address, int backlog) {
  const size_t colon = address.rfind(':');
  int port = -1;
  if (colon != std::string::npos) {
    const char* end = address.data() + address.size();
    if (std::from_chars(address.data() + colon + 1, end, port).ptr != end) port = -1;
  }
  if (colon == std::string::npos || colon == 0 || port < 0 || port > 65535) {
    return absl::InvalidArgumentError(StrCat("--http-listen '", address, "': expected HOST:PORT"));
  }
  std::string host = address.substr(0, colon);
  if (host.size() > 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* found = nullptr;
  const std::string port_text = std::to_string(port);
  if (getaddrinfo(host.c_str(), port_text.c_str(), &hints, &found) != 0 || found == nullptr) {
    return absl::UnavailableError(StrCat("cannot listen on ", address, " for HTTP: the host does not resolve"));
  }
  ListenSocket bound;
  for (addrinfo* a = found; a != nullptr && bound.fd < 0; a = a->ai_next) {
    const int fd = socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
    if (fd < 0) continue;
    const int on = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &on, sizeof on);
    if (a->ai_family == AF_INET6) setsockopt(fd, IPPROTO_IPV6, IPV6_V6ONLY, &on, sizeof on);
    sockaddr_storage name{};
    socklen_t length = sizeof name;
    if (bind(fd, a->ai_addr, a->ai_addrlen) != 0 || listen(fd, backlog) != 0 ||
        getsockname(fd, reinterpret_cast<sockaddr*>(&name), &length) != 0) {
      close(fd);
      continue;
    }
    bound.fd = fd;
    bound.ipv6 = a->ai_family == AF_INET6;
    bound.port = ntohs(bound.ipv6 ? reinterpret_cast<sockaddr_in6*>(&name)->sin6_port
                                  : reinterpret_cast<sockaddr_in*>(&name)->sin_port);
  }
  freeaddrinfo(found);
  if (bound.fd < 0) return absl::UnavailableError(StrCat("cannot listen on ", address, " for HTTP"));
  return bound;
}

absl::StatusOr<std::string> ReadPem(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream text;
  text << in.rdbuf();
  if (!in || text.str().empty()) return absl::UnavailableError(StrCat("HTTPS cannot read ", path));
  return text.str();
}

}  // namespace

std::string JsonQuoted(std::string_view text) {
  std::string out = "\"";
  for (char c : text) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char escaped[8];
      std::snprintf(escaped, sizeof escaped, "\\u%04x", c);
      out += escaped;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

bool HostAllowed(const std::string& host, const std::vector<std::string>& names) {
  const std::string name = HostPart(host);
  if (name.empty()) return false;
  if (name == "localhost" || IsIpLiteral(name)) return true;
  for (const std::string& allowed : names) {
    if (HostPart(allowed) == name) return true;
  }
  return false;
}

struct HttpFront::State {
  HttpFrontOptions options;
  HttpHandler handler;
  std::string scheme = "http";
  int port = 0;
  std::string tls_cert, tls_key;  // PEM text, which the daemon reads from while it runs.
  MHD_Daemon* daemon = nullptr;

  std::mutex mutex;
  std::condition_variable wake;
  bool stopping = false;
  std::set<Connection*> connections;
  std::thread sweeper;

  Clock::time_point NextHeadDeadline() const {
    return Clock::now() + std::chrono::seconds(options.limits.head_seconds);
  }

  // Cuts connections whose next request's head is late: a socket shut down here is seen as
  // closed by its event loop, which then drops the connection (and tells OnConnection).
  void Sweep() {
    std::unique_lock lock(mutex);
    while (!wake.wait_for(lock, std::chrono::milliseconds(200), [this] { return stopping; })) {
      const auto now = Clock::now();
      for (Connection* c : connections) {
        if (c->cut || c->head_deadline > now) continue;
        shutdown(c->fd, SHUT_RDWR);
        c->cut = true;
      }
    }
  }
};

namespace {

using State = HttpFront::State;

Connection* ConnectionOf(MHD_Connection* connection) {
  const MHD_ConnectionInfo* info = MHD_get_connection_info(connection, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
  return info == nullptr ? nullptr : static_cast<Connection*>(info->socket_context);
}

void OnConnection(void* cls, MHD_Connection* connection, void** socket_context,
                  enum MHD_ConnectionNotificationCode code) {
  auto& state = *static_cast<State*>(cls);
  std::lock_guard lock(state.mutex);
  if (code == MHD_CONNECTION_NOTIFY_STARTED) {
    auto* c = new Connection;
    c->fd = MHD_get_connection_info(connection, MHD_CONNECTION_INFO_CONNECTION_FD)->connect_fd;
    c->head_deadline = state.NextHeadDeadline();
    // Past the total, a connection is closed at once, so that its client learns it (the
    // library's own limit, set above this one, would leave it waiting in the backlog).
    if (state.connections.size() >= state.options.limits.max_connections) {
      shutdown(c->fd, SHUT_RDWR);
      c->cut = true;
    }
    state.connections.insert(c);
    *socket_context = c;
  } else if (auto* c = static_cast<Connection*>(*socket_context); c != nullptr) {
    state.connections.erase(c);
    delete c;
    *socket_context = nullptr;
  }
}

void OnRequestDone(void* cls, MHD_Connection* connection, void**, enum MHD_RequestTerminationCode) {
  auto& state = *static_cast<State*>(cls);
  std::lock_guard lock(state.mutex);
  if (Connection* c = ConnectionOf(connection); c != nullptr) c->head_deadline = state.NextHeadDeadline();
}

MHD_Result CollectValue(void* cls, enum MHD_ValueKind, const char* key, const char* value) {
  if (key != nullptr) (*static_cast<std::map<std::string, std::string>*>(cls))[key] = value == nullptr ? "" : value;
  return MHD_YES;
}

ssize_t ReadStream(void* cls, uint64_t, char* buffer, size_t max) {
  const int64_t n = (*static_cast<std::function<int64_t(char*, size_t)>*>(cls))(buffer, max);
  if (n > 0) return static_cast<ssize_t>(n);
  return n == 0 ? MHD_CONTENT_READER_END_OF_STREAM : MHD_CONTENT_READER_END_WITH_ERROR;
}

void FreeStream(void* cls) { delete static_cast<std::function<int64_t(char*, size_t)>*>(cls); }

HttpAnswer Refusal(int status, std::string_view code, std::string_view message) {
  HttpAnswer answer;
  answer.status = status;
  answer.headers.emplace_back("Content-Type", "application/json");
  answer.body = StrCat("{\"code\": ", JsonQuoted(code), ", \"message\": ", JsonQuoted(message), "}");
  return answer;
}

HttpAnswer Handle(State& state, MHD_Connection* connection, const char* url, const char* method) {
  HttpRequest request;
  request.method = method;
  request.path = url;
  std::map<std::string, std::string> headers;
  MHD_get_connection_values(connection, MHD_HEADER_KIND, CollectValue, &headers);
  for (auto& [name, value] : headers) request.headers[Lower(name)] = std::move(value);
  MHD_get_connection_values(connection, MHD_GET_ARGUMENT_KIND, CollectValue, &request.query);
  const std::string host = request.header("host");
  if (host.empty()) return Refusal(400, "INVALID_ARGUMENT", "the request names no Host");
  if (!HostAllowed(host, state.options.host_names)) {
    return Refusal(421, "PERMISSION_DENIED",
                   StrCat("this server does not answer to the name '", host.substr(0, 256),
                          "'; lsqsurfd --http-host NAME adds a name it answers to"));
  }
  try {
    return state.handler(request);
  } catch (const std::exception& e) {
    spdlog::error("http: {} {} failed: {}", request.method, request.path.substr(0, 256), e.what());
    return Refusal(500, "INTERNAL", "the request failed inside the server");
  }
}

// Connections the library may hold beyond HttpLimits::max_connections: those over it, accepted
// only to be closed at once.
constexpr unsigned kClosingHeadroom = 64;

// Request bodies this front takes (and drops unread): none of its routes needs one.
constexpr size_t kMaxBodyBytes = 64 << 10;

// Called once the head has come, then with the body's pieces if any, then with none: the answer
// goes at that last call (the library refuses one queued mid-body). A body past kMaxBodyBytes
// closes the connection. The head deadline runs on until the answer is queued, so a body that
// trickles is cut like a head that does.
MHD_Result OnRequest(void* cls, MHD_Connection* connection, const char* url, const char* method, const char*,
                     const char*, size_t* upload_data_size, void** request_context) {
  auto& state = *static_cast<State*>(cls);
  Connection* c = ConnectionOf(connection);
  if (*request_context == nullptr) {
    *request_context = &state;
    std::lock_guard lock(state.mutex);
    if (c != nullptr) {
      c->body_bytes = 0;
      c->last_request = ++c->requests >= state.options.limits.max_requests_per_connection;
    }
    return MHD_YES;
  }
  if (*upload_data_size > 0) {
    const size_t piece = *upload_data_size;
    *upload_data_size = 0;
    std::lock_guard lock(state.mutex);
    if (c != nullptr && (c->body_bytes += piece) > kMaxBodyBytes) return MHD_NO;
    return MHD_YES;
  }
  bool last = false;
  {
    std::lock_guard lock(state.mutex);
    if (c != nullptr) {
      c->head_deadline = Clock::time_point::max();
      last = c->last_request;
    }
  }
  HttpAnswer answer = Handle(state, connection, url, method);
  MHD_Response* response = nullptr;
  if (answer.stream) {
    const uint64_t size = answer.stream_size < 0 ? MHD_SIZE_UNKNOWN : static_cast<uint64_t>(answer.stream_size);
    response = MHD_create_response_from_callback(
        size, 64 << 10, ReadStream, new std::function<int64_t(char*, size_t)>(std::move(answer.stream)), FreeStream);
  } else {
    response = MHD_create_response_from_buffer(answer.body.size(), answer.body.data(), MHD_RESPMEM_MUST_COPY);
  }
  if (response == nullptr) return MHD_NO;
  for (const auto& [name, value] : answer.headers) MHD_add_response_header(response, name.c_str(), value.c_str());
  if (last) MHD_add_response_header(response, MHD_HTTP_HEADER_CONNECTION, "close");
  const MHD_Result queued = MHD_queue_response(connection, static_cast<unsigned>(answer.status), response);
  MHD_destroy_response(response);
  return queued;
}

// The library's own messages (refused connections, heads too long) are a client's doing: kept
// at debug level so that a flood of them cannot fill the log.
void LogLibraryMessage(void*, const char* format, va_list args) {
  if (!spdlog::should_log(spdlog::level::debug)) return;
  char text[512];
  std::vsnprintf(text, sizeof text, format, args);
  spdlog::debug("http: {}", text);
}

}  // namespace

HttpFront::HttpFront(std::unique_ptr<State> state) : state_(std::move(state)) {}

absl::StatusOr<std::unique_ptr<HttpFront>> HttpFront::Start(const HttpFrontOptions& options, HttpHandler handler) {
  auto state = std::make_unique<State>();
  state->options = options;
  state->handler = std::move(handler);
  const HttpLimits& limits = options.limits;
  unsigned flags = MHD_USE_EPOLL_INTERNAL_THREAD | MHD_USE_ERROR_LOG;
  if (!options.tls_cert_path.empty()) {
    if (MHD_is_feature_supported(MHD_FEATURE_TLS) != MHD_YES) {
      return absl::UnavailableError("HTTPS: this build of libmicrohttpd has no TLS");
    }
    auto cert = ReadPem(options.tls_cert_path);
    if (!cert.ok()) return cert.status();
    auto key = ReadPem(options.tls_key_path);
    if (!key.ok()) return key.status();
    state->tls_cert = *std::move(cert);
    state->tls_key = *std::move(key);
    state->scheme = "https";
    flags |= MHD_USE_TLS;
  }
  auto bound = Listen(options.listen, limits.listen_backlog);
  if (!bound.ok()) return bound.status();
  if (bound->ipv6) flags |= MHD_USE_IPv6;
  state->port = bound->port;
  auto item = [](MHD_OPTION option, intptr_t value, void* pointer = nullptr) {
    return MHD_OptionItem{option, value, pointer};
  };
  std::vector<MHD_OptionItem> items = {
      item(MHD_OPTION_EXTERNAL_LOGGER, reinterpret_cast<intptr_t>(&LogLibraryMessage)),
      item(MHD_OPTION_LISTEN_SOCKET, bound->fd),
      item(MHD_OPTION_CONNECTION_MEMORY_LIMIT, static_cast<intptr_t>(limits.connection_memory_bytes)),
      item(MHD_OPTION_CONNECTION_LIMIT, limits.max_connections + kClosingHeadroom),
      item(MHD_OPTION_PER_IP_CONNECTION_LIMIT, limits.max_connections_per_peer),
      item(MHD_OPTION_CONNECTION_TIMEOUT, limits.idle_seconds),
      item(MHD_OPTION_THREAD_POOL_SIZE, std::max(1u, limits.threads)),
      item(MHD_OPTION_NOTIFY_CONNECTION, reinterpret_cast<intptr_t>(&OnConnection), state.get()),
      item(MHD_OPTION_NOTIFY_COMPLETED, reinterpret_cast<intptr_t>(&OnRequestDone), state.get()),
  };
  if (state->scheme == "https") {
    items.push_back(item(MHD_OPTION_HTTPS_MEM_CERT, 0, state->tls_cert.data()));
    items.push_back(item(MHD_OPTION_HTTPS_MEM_KEY, 0, state->tls_key.data()));
  }
  items.push_back(item(MHD_OPTION_END, 0));
  state->daemon = MHD_start_daemon(flags, 0, nullptr, nullptr, &OnRequest, state.get(), MHD_OPTION_ARRAY, items.data(),
                                   MHD_OPTION_END);
  if (state->daemon == nullptr) {
    close(bound->fd);
    return absl::UnavailableError(
        StrCat("cannot serve HTTP on ", options.listen,
               state->scheme == "https" ? " (do the TLS files hold a PEM key and its certificate?)" : ""));
  }
  State* raw = state.get();
  state->sweeper = std::thread([raw] { raw->Sweep(); });
  return std::unique_ptr<HttpFront>(new HttpFront(std::move(state)));
}

HttpFront::~HttpFront() {
  {
    std::lock_guard lock(state_->mutex);
    state_->stopping = true;
  }
  state_->wake.notify_all();
  state_->sweeper.join();
  MHD_stop_daemon(state_->daemon);  // Also closes the listening socket.
}

std::string HttpFront::scheme() const { return state_->scheme; }
int HttpFront::port() const { return state_->port; }

size_t HttpFront::open_connections() const {
  std::lock_guard lock(state_->mutex);
  return state_->connections.size();
}

}  // namespace lsqsurf::server
