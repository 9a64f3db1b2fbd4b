// The HTTP front (server/http_front.h) under the clients that took the old one down: endless
// headers, slow and silent connections, too many connections, foreign Host names, endless
// keep-alive. Raw sockets on loopback, from several loopback source addresses (127.0.0.0/8 is all
// loopback on Linux) so that one "peer" can be held to its share while another is served.
#include "server/http_front.h"

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

namespace lsqsurf::server {
namespace {

using Clock = std::chrono::steady_clock;

// An owned socket connected from `source` to 127.0.0.1:port.
class Socket {
 public:
  Socket(int port, const char* source = "127.0.0.1") : fd_(socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0)) {
    sockaddr_in from{};
    from.sin_family = AF_INET;
    inet_pton(AF_INET, source, &from.sin_addr);
    EXPECT_EQ(bind(fd_, reinterpret_cast<sockaddr*>(&from), sizeof from), 0);
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(static_cast<uint16_t>(port));
    inet_pton(AF_INET, "127.0.0.1", &to.sin_addr);
    connected_ = connect(fd_, reinterpret_cast<sockaddr*>(&to), sizeof to) == 0;
    timeval timeout{5, 0};
    setsockopt(fd_, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof timeout);
  }
  ~Socket() { close(fd_); }
  Socket(const Socket&) = delete;
  Socket& operator=(const Socket&) = delete;

  bool connected() const { return connected_; }
  bool Send(const std::string& bytes) {
    size_t sent = 0;
    while (sent < bytes.size()) {
      const ssize_t n = send(fd_, bytes.data() + sent, bytes.size() - sent, MSG_NOSIGNAL);
      if (n <= 0) return false;
      sent += static_cast<size_t>(n);
    }
    return true;
  }
  // Reads what comes within `wait`, up to the end of one answer with a body of Content-Length
  // bytes, or the connection's end. `closed` says whether it ended (orderly or reset).
  std::string Read(std::chrono::milliseconds wait, bool* closed = nullptr) {
    std::string got;
    const auto until = Clock::now() + wait;
    bool ended = false;
    while (!ended && !AnswerComplete(got)) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now()).count();
      if (left <= 0) break;
      pollfd p{fd_, POLLIN, 0};
      if (poll(&p, 1, static_cast<int>(left)) <= 0) break;
      char buffer[4096];
      const ssize_t n = recv(fd_, buffer, sizeof buffer, 0);
      if (n <= 0) ended = true;
      if (n > 0) got.append(buffer, static_cast<size_t>(n));
    }
    if (closed != nullptr) *closed = ended;
    return got;
  }
  // Whether the server ends the connection within `wait` (any bytes it sends first are read).
  bool ClosedWithin(std::chrono::milliseconds wait) {
    const auto until = Clock::now() + wait;
    while (Clock::now() < until) {
      bool closed = false;
      Read(std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now()), &closed);
      if (closed) return true;
    }
    return false;
  }

 private:
  static bool AnswerComplete(const std::string& got) {
    const size_t head_end = got.find("\r\n\r\n");
    if (head_end == std::string::npos) return false;
    const size_t length_at = got.find("Content-Length: ");
    if (length_at == std::string::npos || length_at > head_end) return false;
    const size_t length = std::stoul(got.substr(length_at + 16));
    return got.size() >= head_end + 4 + length;
  }
  int fd_;
  bool connected_ = false;
};

std::string Get(int port, const std::string& host = "127.0.0.1") {
  return "GET /hello HTTP/1.1\r\nHost: " + host + ":" + std::to_string(port) + "\r\n\r\n";
}

int64_t ResidentBytes() {
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stoll(line.substr(6)) << 10;
  }
  return -1;
}

class HttpFrontTest : public ::testing::Test {
 protected:
  void Start(HttpFrontOptions options = {}) {
    auto front = HttpFront::Start(options, [this](const HttpRequest& request) {
      ++answered_;
      HttpAnswer answer;
      answer.body = "hello from " + request.path;
      return answer;
    });
    ASSERT_TRUE(front.ok()) << front.status();
    front_ = *std::move(front);
  }
  int port() const { return front_->port(); }
  // Whether the front's count of open connections comes to `count` within 5 s.
  bool OpenConnectionsReach(size_t count) const {
    const auto until = Clock::now() + std::chrono::seconds(5);
    while (front_->open_connections() != count) {
      if (Clock::now() > until) return false;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return true;
  }
  // A fresh request from a well-behaved client: the answer's text and how long it took.
  std::pair<std::string, double> Fresh() {
    const auto start = Clock::now();
    Socket client(port());
    if (!client.Send(Get(port()))) return {"", 1e9};
    std::string answer = client.Read(std::chrono::seconds(5));
    return {answer, std::chrono::duration<double>(Clock::now() - start).count()};
  }

  std::atomic<int> answered_{0};
  std::unique_ptr<HttpFront> front_;
};

bool IsOk(const std::string& answer) { return answer.rfind("HTTP/1.1 200", 0) == 0; }

TEST_F(HttpFrontTest, EndlessHeadersAreCutEarlyAndCostNoMemory) {
  Start();
  // A head that fits is answered: the bound is not a refusal of every header.
  Socket fits(port());
  ASSERT_TRUE(fits.Send("GET /fits HTTP/1.1\r\nHost: localhost\r\nX-Pad: " + std::string(16 << 10, 'a') + "\r\n\r\n"));
  EXPECT_TRUE(IsOk(fits.Read(std::chrono::seconds(5))));

  const int64_t before = ResidentBytes();
  Socket attacker(port());
  ASSERT_TRUE(attacker.Send("GET / HTTP/1.1\r\nHost: localhost\r\n"));
  const std::string line = "X-Endless: " + std::string(1000, 'x') + "\r\n";
  size_t sent = 0;
  while (sent < (size_t{256} << 20) && attacker.Send(line)) sent += line.size();
  // The server stopped taking bytes after its 32 KiB, give or take what the kernel buffers.
  EXPECT_LT(sent, size_t{16} << 20);
  EXPECT_LT(ResidentBytes() - before, int64_t{64} << 20);
  EXPECT_EQ(answered_.load(), 1);
  const auto [answer, seconds] = Fresh();
  EXPECT_TRUE(IsOk(answer)) << answer;
}

TEST_F(HttpFrontTest, TricklingAndSilentConnectionsNeitherHoldThePageNorStay) {
  HttpFrontOptions options;
  options.limits.head_seconds = 2;
  Start(options);
  std::vector<std::unique_ptr<Socket>> silent, trickling;
  for (int i = 0; i < 80; ++i) silent.push_back(std::make_unique<Socket>(port(), "127.0.0.2"));
  for (int i = 0; i < 8; ++i) {
    trickling.push_back(std::make_unique<Socket>(port(), "127.0.0.3"));
    ASSERT_TRUE(trickling.back()->Send("GET / HTTP/1.1\r\nHost: localhost\r\nX-Slow: "));
  }
  std::atomic<bool> stop{false};
  std::thread trickle([&] {
    while (!stop) {  // A byte a connection every 100 ms: each byte would reset a per-byte timeout.
      for (auto& s : trickling) s->Send("x");
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  });
  // Throughout, and past the point where the slow heads are due, a fresh request is answered at once.
  const auto start = Clock::now();
  double slowest = 0;
  while (Clock::now() - start < std::chrono::milliseconds(3500)) {
    const auto [answer, seconds] = Fresh();
    EXPECT_TRUE(IsOk(answer)) << answer;
    slowest = std::max(slowest, seconds);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_LT(slowest, 2.0);
  // By then every late head is cut, the trickling ones though they never stopped sending.
  for (auto& s : trickling) EXPECT_TRUE(s->ClosedWithin(std::chrono::milliseconds(1500)));
  for (auto& s : silent) EXPECT_TRUE(s->ClosedWithin(std::chrono::milliseconds(200)));
  stop = true;
  trickle.join();
}

TEST_F(HttpFrontTest, APeerPastItsShareIsRefusedAndOthersAreServed) {
  HttpFrontOptions options;
  options.limits.max_connections_per_peer = 4;
  options.limits.max_connections = 8;
  Start(options);
  // Four kept-alive connections from one address, each answered once (so each is accepted).
  std::vector<std::unique_ptr<Socket>> held;
  for (int i = 0; i < 4; ++i) {
    held.push_back(std::make_unique<Socket>(port(), "127.0.0.2"));
    ASSERT_TRUE(held.back()->Send(Get(port())));
    ASSERT_TRUE(IsOk(held.back()->Read(std::chrono::seconds(5))));
  }
  Socket fifth(port(), "127.0.0.2");
  fifth.Send(Get(port()));
  EXPECT_TRUE(fifth.ClosedWithin(std::chrono::seconds(2)));
  EXPECT_TRUE(IsOk(Fresh().first));
  // The fresh client has gone; the count holds it until the server has seen it go.
  ASSERT_TRUE(OpenConnectionsReach(4));

  // Past the total: four more from another address fill it, and the next, from a third, is refused.
  // Each is answered before the next connects: the library's threads accept in no fixed order, so
  // an unanswered one might be counted after the one meant to be refused.
  for (int i = 0; i < 4; ++i) {
    held.push_back(std::make_unique<Socket>(port(), "127.0.0.3"));
    ASSERT_TRUE(held.back()->Send(Get(port())));
    ASSERT_TRUE(IsOk(held.back()->Read(std::chrono::seconds(5))));
  }
  Socket over(port(), "127.0.0.4");
  over.Send(Get(port()));
  EXPECT_TRUE(over.ClosedWithin(std::chrono::seconds(2)));
  held.clear();  // Once they go, the port serves again.
  bool served = false;
  for (int i = 0; i < 50 && !served; ++i) {
    served = IsOk(Fresh().first);
    if (!served) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_TRUE(served);
}

TEST_F(HttpFrontTest, OnlyItsOwnHostNamesAreAnswered) {
  HttpFrontOptions options;
  options.host_names = {"lsqsurf.example"};
  Start(options);
  auto ask = [&](const std::string& request) {
    Socket client(port());
    client.Send(request);
    return client.Read(std::chrono::seconds(5));
  };
  for (const std::string host : {"127.0.0.1", "localhost", "[::1]", "LSQSURF.example.", "10.1.2.3"}) {
    EXPECT_TRUE(IsOk(ask(Get(port(), host)))) << host;
  }
  // A rebinding page's own name, and names that merely contain an allowed one.
  for (const std::string host : {"evil.example", "lsqsurf.example.evil.example", "localhost.evil.example"}) {
    const std::string answer = ask(Get(port(), host));
    EXPECT_EQ(answer.rfind("HTTP/1.1 421", 0), 0u) << host << ": " << answer;
    EXPECT_NE(answer.find("--http-host"), std::string::npos);
  }
  const std::string no_host = ask("GET / HTTP/1.0\r\n\r\n");
  EXPECT_EQ(no_host.substr(0, no_host.find("\r\n")).find(" 400 "), 8u) << no_host;
  EXPECT_EQ(answered_.load(), 5);

  EXPECT_TRUE(HostAllowed("127.0.0.1:8080", {}));
  EXPECT_TRUE(HostAllowed("[2001:db8::1]:443", {}));
  EXPECT_FALSE(HostAllowed("example.com:8080", {}));
  EXPECT_FALSE(HostAllowed("", {"example.com"}));
  EXPECT_TRUE(HostAllowed("Example.COM:8080", {"example.com"}));
}

TEST_F(HttpFrontTest, AKeptAliveConnectionEndsAfterItsRequests) {
  HttpFrontOptions options;
  options.limits.max_requests_per_connection = 3;
  Start(options);
  Socket client(port());
  for (int i = 1; i <= 3; ++i) {
    ASSERT_TRUE(client.Send(Get(port())));
    const std::string answer = client.Read(std::chrono::seconds(5));
    ASSERT_TRUE(IsOk(answer)) << i;
    EXPECT_EQ(answer.find("Connection: close") != std::string::npos, i == 3) << answer;
  }
  EXPECT_TRUE(client.ClosedWithin(std::chrono::seconds(2)));
}

TEST_F(HttpFrontTest, BadAddressesAndTlsFilesAreRefused) {
  HttpFrontOptions options;
  options.listen = "no-port";
  EXPECT_EQ(HttpFront::Start(options, {}).status().code(), absl::StatusCode::kInvalidArgument);
  options.listen = "127.0.0.1:0";
  options.tls_cert_path = "/nonexistent/cert.pem";
  options.tls_key_path = "/nonexistent/key.pem";
  EXPECT_EQ(HttpFront::Start(options, {}).status().code(), absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace lsqsurf::server
