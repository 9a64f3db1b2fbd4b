// tests/e2e/harness.h — the real lsqsurfd on a free loopback port, and the real lsqsurf client.
#pragma once

#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

namespace lsqsurf::testing {

class Server {
 public:
  // Starts lsqsurfd on 127.0.0.1:0 and reads the bound address from its first stdout line. Its
  // log goes to `log` (discarded when empty).
  void Start(const std::filesystem::path& data_dir, std::vector<std::string> extra = {}, const std::string& log = "") {
    int out[2];
    ASSERT_EQ(::pipe(out), 0);
    pid_ = ::fork();
    ASSERT_GE(pid_, 0);
    if (pid_ == 0) {
      ::dup2(out[1], STDOUT_FILENO);
      const int err =
          log.empty() ? ::open("/dev/null", O_WRONLY) : ::open(log.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
      ::dup2(err, STDERR_FILENO);
      ::close(out[0]);
      std::vector<std::string> args = {LSQSURFD_PATH, "--listen", "127.0.0.1:0", "--data-dir", data_dir.string()};
      args.insert(args.end(), extra.begin(), extra.end());
      std::vector<char*> argv;
      for (auto& a : args) argv.push_back(a.data());
      argv.push_back(nullptr);
      ::execv(argv[0], argv.data());
      ::_exit(127);
    }
    ::close(out[1]);
    FILE* f = ::fdopen(out[0], "r");
    char line[256] = {0};
    ASSERT_NE(std::fgets(line, sizeof(line), f), nullptr) << "server printed nothing";
    std::fclose(f);
    std::string s(line);
    const std::string prefix = "listening on ";
    ASSERT_EQ(s.rfind(prefix, 0), 0u) << s;
    address_ = s.substr(prefix.size());
    while (!address_.empty() && (address_.back() == '\n' || address_.back() == '\r')) address_.pop_back();
  }
  void Kill(int signal) {
    if (pid_ <= 0) return;
    ::kill(pid_, signal);
    int status = 0;
    ::waitpid(pid_, &status, 0);
    pid_ = -1;
  }
  // Sends a signal without waiting for the server to act on it (SIGHUP: reload).
  void Signal(int signal) const {
    if (pid_ > 0) ::kill(pid_, signal);
  }
  ~Server() { Kill(SIGKILL); }
  const std::string& address() const { return address_; }
  bool running() const { return pid_ > 0; }

 private:
  pid_t pid_ = -1;
  std::string address_;
};

struct ClientRun {
  int code = -1;
  std::string output;  // stdout and stderr together.
};

// Runs a shell command line; its exit code and its stdout and stderr together.
inline ClientRun Shell(const std::string& command) {
  ClientRun r;
  FILE* p = ::popen(("(" + command + ") 2>&1").c_str(), "r");
  std::array<char, 4096> buf;
  size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0) r.output.append(buf.data(), n);
  const int status = ::pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

inline ClientRun Client(const std::string& address, const std::string& args) {
  return Shell(std::string(LSQSURF_PATH) + " --server " + address + " " + args);
}

inline std::string Trim(std::string s) {
  while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
  return s;
}

}  // namespace lsqsurf::testing
