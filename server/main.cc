// lsqsurfd — the reconstruction server. Parses flags, wires the job service to gRPC, waits.
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <csignal>
#include <cstdio>
#include <thread>

#include "server/metrics.h"
#include "server/reconstruction_service.h"
#include "worker/jobs/job_service.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/postgres_store.h"

namespace {

// Opens the job and blob stores the flags ask for into `options`; the defaults (SQLite and
// files under the data directory) are left to the job service.
absl::Status OpenStores(const std::string& store, const std::string& blob_dir, int connections,
                        lsqsurf::jobs::JobServiceOptions& options) {
  namespace jobs = lsqsurf::jobs;
  if (!blob_dir.empty()) {
    auto blobs = jobs::LocalDirBlobStore::Open(blob_dir);
    if (!blobs.ok()) return blobs.status();
    options.blobs = *std::move(blobs);
  }
  if (store.empty() || store == "sqlite") return absl::OkStatus();
  if (store.rfind("postgresql://", 0) != 0 && store.rfind("postgres://", 0) != 0) {
    return absl::InvalidArgumentError("--store takes 'sqlite' or a postgresql://user@host:port/database URL");
  }
  auto shared = jobs::PostgresJobStore::Open(store, connections);
  if (!shared.ok()) return shared.status();
  if (options.blobs == nullptr) options.blobs = std::make_shared<jobs::PostgresBlobStore>((*shared)->pool());
  options.store = *std::move(shared);
  return absl::OkStatus();
}

// The command line: the job service's options, and the server's own.
struct ServerFlags {
  std::string listen = "127.0.0.1:50051";
  int64_t max_upload_mib = 1024;
  std::string store = "sqlite", blob_dir, metrics_listen;
  int store_connections = 8;
  double lease_seconds = 0;  // Set from JobServiceOptions::lease, whose default it shows.
  bool parameter_reference = false;
};

void DefineFlags(CLI::App& app, ServerFlags& flags, lsqsurf::jobs::JobServiceOptions& options) {
  app.add_option("--listen", flags.listen, "HOST:PORT to listen on; port 0 picks a free port")->capture_default_str();
  app.add_option("--data-dir", options.data_dir, "where jobs, inputs and results are kept")->capture_default_str();
  app.add_option("--workers", options.workers, "jobs that run at once")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  app.add_option("--max-queue", options.max_queue, "queued jobs before submissions are refused")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  app.add_option("--max-points", options.max_points, "largest accepted cloud")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{16}, int64_t{2'000'000'000}));
  app.add_option("--max-cells", options.max_cells, "largest accepted volume mesh, in cells")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{1}, int64_t{2'000'000'000}));
  app.add_option("--max-upload-mib", flags.max_upload_mib, "largest accepted upload, MiB")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{1}, int64_t{1} << 20));
  app.add_option("--max-renders", options.max_renders, "pictures drawn at once by Render; more are refused")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  app.add_option("--max-attempts", options.max_attempts,
                 "starts cut short by a crash after which a job is failed (a graceful stop does not count)")
      ->capture_default_str()
      ->check(CLI::Range(1, 100));
  app.add_option("--min-points", options.min_points, "smallest accepted surface cloud")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{4}, int64_t{1'000'000}));
  app.add_option("--store", flags.store,
                 "where jobs are kept: 'sqlite' (a file in the data directory, one server) or a "
                 "postgresql://user@host:port/database URL that several servers share (a password is better "
                 "kept in PGPASSWORD or ~/.pgpass than in the URL)")
      ->capture_default_str();
  app.add_option("--blob-dir", flags.blob_dir,
                 "where uploads and results are kept; default: the data directory with --store sqlite, the "
                 "database with --store postgresql:// (give a shared volume here to keep them out of it)");
  app.add_option("--name", options.name, "this server's name among those sharing a store (default: host name)");
  app.add_option("--lease-seconds", flags.lease_seconds,
                 "a running job stays this server's this long without a renewal: how long the jobs of a server "
                 "that died wait before another runs them")
      ->capture_default_str()
      ->check(CLI::Range(1.0, 3600.0));
  app.add_option("--store-connections", flags.store_connections, "connections to a PostgreSQL store")
      ->capture_default_str()
      ->check(CLI::Range(2, 64));
  app.add_option("--metrics-listen", flags.metrics_listen,
                 "HOST:PORT on which to serve Prometheus metrics at /metrics (off when not given)");
  app.set_config("--config", "", "read options from this TOML/INI file");
  app.add_flag("--parameter-reference", flags.parameter_reference,
               "print every method's parameters (and the view options) as Markdown, then exit");
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurfd: surface reconstruction server"};
  ServerFlags flags;
  lsqsurf::jobs::JobServiceOptions options;
  options.data_dir = "lsqsurf-data";
  flags.lease_seconds = std::chrono::duration<double>(options.lease).count();
  DefineFlags(app, flags, options);
  CLI11_PARSE(app, argc, argv);
  if (flags.parameter_reference) {
    std::fputs(lsqsurf::jobs::ParameterReference().c_str(), stdout);
    return 0;
  }
  options.max_input_bytes = flags.max_upload_mib << 20;
  options.lease = std::chrono::milliseconds(static_cast<int64_t>(flags.lease_seconds * 1000));

  // Logs go to stderr; stdout carries only the "listening on" line that scripts wait for.
  spdlog::set_default_logger(spdlog::stderr_color_mt("lsqsurfd"));
  spdlog::set_pattern("%Y-%m-%d %H:%M:%S.%e %^%l%$ %v");

  // Block the shutdown signals in every thread; one thread waits for them below.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  if (absl::Status s = OpenStores(flags.store, flags.blob_dir, flags.store_connections, options); !s.ok()) {
    spdlog::critical("cannot start: {}", s.ToString());
    return 1;
  }
  std::shared_ptr<lsqsurf::server::Metrics> metrics;
  if (!flags.metrics_listen.empty()) {
    auto started = lsqsurf::server::Metrics::Start(flags.metrics_listen);
    if (!started.ok()) {
      spdlog::critical("cannot start: {}", started.status().ToString());
      return 1;
    }
    metrics = *std::move(started);
    options.events = metrics;
    spdlog::info("metrics on http://{}/metrics", flags.metrics_listen);
  }
  auto jobs = lsqsurf::jobs::JobService::Open(options);
  if (!jobs.ok()) {
    spdlog::critical("cannot start: {}", jobs.status().ToString());
    return 1;
  }
  if (metrics != nullptr) metrics->Watch(jobs->get());
  lsqsurf::server::ReconstructionService service(**jobs, metrics.get());
  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort(flags.listen, grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&service);
  builder.SetMaxReceiveMessageSize(16 << 20);
  builder.SetMaxSendMessageSize(16 << 20);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (!server || port == 0) {
    spdlog::critical("cannot listen on {}", flags.listen);
    return 1;
  }
  server->GetHealthCheckService()->SetServingStatus(lsqsurf::server::ReconstructionService::kServiceName, true);
  const std::string host = flags.listen.substr(0, flags.listen.rfind(':'));
  std::printf("listening on %s:%d\n", host.c_str(), port);
  std::fflush(stdout);
  spdlog::info("serving on {}:{}", host, port);

  // Readiness (the API's health status) follows the store; liveness (the server's) does not.
  std::atomic<bool> stopping{false};
  std::thread readiness([&] {
    bool serving = true;
    while (!stopping) {
      std::this_thread::sleep_for(std::chrono::milliseconds(500));
      if (stopping) break;
      const bool reachable = (*jobs)->StoreReachable();
      if (reachable == serving) continue;
      serving = reachable;
      server->GetHealthCheckService()->SetServingStatus(lsqsurf::server::ReconstructionService::kServiceName, serving);
    }
  });
  std::thread waiter([&] {
    int signal = 0;
    sigwait(&signals, &signal);
    spdlog::info("signal {} received: shutting down", signal);
    stopping = true;
    readiness.join();
    // Interrupted jobs go back to the queue on disk first, then open streams are closed.
    server->GetHealthCheckService()->SetServingStatus(false);
    (*jobs)->Shutdown();
    server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(3));
  });
  server->Wait();
  waiter.join();
  if (metrics != nullptr) metrics->Stop();
  spdlog::info("stopped");
  return 0;
}
