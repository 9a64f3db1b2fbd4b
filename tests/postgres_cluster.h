// tests/postgres_cluster.h — a throwaway PostgreSQL server on loopback for one test process.
//
// initdb in a fresh folder, started on a free port with durability off (a test's data need not
// survive a power cut), stopped and removed at the end. PostgreSQL refuses to run as root, so
// under root the server runs as the "postgres" user that Debian's package makes.
#pragma once

#include <pwd.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <memory>
#include <random>
#include <string>

#include "tests/test_dir.h"
#include "worker/jobs/store/postgres_connection.h"

namespace lsqsurf::testing {

class PostgresCluster {
 public:
  // Null, with the reason in `why_not`, where PostgreSQL's server programs are missing.
  static std::unique_ptr<PostgresCluster> Start(std::string* why_not) {
    const std::string bin = ServerBinaries();
    if (bin.empty()) {
      *why_not = "PostgreSQL's server programs (initdb, pg_ctl) are not installed: scripts/install-deps.sh adds them";
      return nullptr;
    }
    std::unique_ptr<PostgresCluster> cluster(new PostgresCluster);
    cluster->bin_ = bin;
    cluster->dir_ = std::filesystem::temp_directory_path() / ("lsqsurf-pg-" + std::to_string(::getpid()) + "-" +
                                                              std::to_string(std::random_device{}() % 100000));
    std::filesystem::remove_all(cluster->dir_);
    std::filesystem::create_directories(cluster->dir_);
    if (::geteuid() == 0) {
      const passwd* user = ::getpwnam("postgres");
      if (user == nullptr) {
        *why_not = "running as root and there is no 'postgres' user to run the server as";
        return nullptr;
      }
      if (::chown(cluster->dir_.c_str(), user->pw_uid, user->pw_gid) != 0) {
        *why_not = "cannot hand the cluster folder to the postgres user";
        return nullptr;
      }
      cluster->as_user_ = "runuser -u postgres -- ";
    }
    const std::string d = cluster->dir_.string();
    if (!cluster->Run("initdb -D " + d + "/data -A trust -U lsqsurf --no-sync -E UTF8 --locale=C", "initdb.log")) {
      *why_not = "initdb failed; see " + d + "/initdb.log";
      return nullptr;
    }
    for (int attempt = 0; attempt < 5; ++attempt) {
      cluster->port_ = FreeLoopbackPort();
      const std::string options = "-p " + std::to_string(cluster->port_) + " -k " + d +
                                  " -c listen_addresses=127.0.0.1 -c fsync=off -c synchronous_commit=off"
                                  " -c full_page_writes=off -c max_connections=200";
      if (cluster->Run("pg_ctl -D " + d + "/data -l " + d + "/server.log -w -t 60 -o '" + options + "' start",
                       "pg_ctl.log")) {
        cluster->running_ = true;
        return cluster;
      }
    }
    *why_not = "the PostgreSQL server did not start; see " + d + "/server.log";
    return nullptr;
  }

  ~PostgresCluster() {
    if (running_) Run("pg_ctl -D " + dir_.string() + "/data -m immediate stop", "stop.log");
    std::error_code ec;
    std::filesystem::remove_all(dir_, ec);
  }

  // A new empty database on the server; its connection URL.
  std::string NewDatabase() {
    const std::string name = "test" + std::to_string(++databases_);
    auto conn = jobs::pg::Connect(Url("postgres"));
    if (!conn.ok()) return "";
    const bool made = jobs::pg::Exec(*conn, "CREATE DATABASE " + name).ok();
    jobs::pg::Close(*conn);
    return made ? Url(name) : "";
  }

  std::string Url(const std::string& database) const {
    return "postgresql://lsqsurf@127.0.0.1:" + std::to_string(port_) + "/" + database;
  }
  int port() const { return port_; }

 private:
  PostgresCluster() = default;

  static std::string ServerBinaries() {
    std::error_code ec;
    for (const auto& version : std::filesystem::directory_iterator("/usr/lib/postgresql", ec)) {
      if (std::filesystem::exists(version.path() / "bin" / "initdb")) return (version.path() / "bin").string();
    }
    return "";
  }

  bool Run(const std::string& command, const std::string& log) const {
    const std::string line = as_user_ + bin_ + "/" + command + " > " + (dir_ / log).string() + " 2>&1";
    return std::system(line.c_str()) == 0;
  }

  std::string bin_, as_user_;
  std::filesystem::path dir_;
  int port_ = 0;
  bool running_ = false;
  int databases_ = 0;
};

// One server for the whole test process, started on first use and stopped when it exits; null
// with the reason where none can start.
inline PostgresCluster* SharedPostgresCluster(std::string* why_not) {
  static std::string reason;
  static std::unique_ptr<PostgresCluster> cluster = PostgresCluster::Start(&reason);
  *why_not = reason;
  return cluster.get();
}

}  // namespace lsqsurf::testing
