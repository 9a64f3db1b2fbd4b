// lsqsurfd — the reconstruction server. Parses flags, wires the job service to gRPC, waits.
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <thread>
#include <vector>

#include "server/http_gateway.h"
#include "server/limits.h"
#include "server/metrics.h"
#include "server/server.h"
#include "server/tls.h"
#include "server/tokens.h"
#include "worker/core/address.h"
#include "worker/core/strings.h"
#include "worker/jobs/job_service.h"
#include "worker/jobs/method_registry.h"
#if LSQSURF_WITH_POSTGRESQL
#include "worker/jobs/store/postgres_store.h"
#endif

namespace {

// How long the server's own teardown may take once every job is safely back in the store.
constexpr std::chrono::seconds kTeardownGrace{15};

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
#if LSQSURF_WITH_POSTGRESQL
  auto shared = jobs::PostgresJobStore::Open(store, jobs::RegistrySpecTables(), connections);
  if (!shared.ok()) return shared.status();
  if (options.blobs == nullptr) options.blobs = std::make_shared<jobs::PostgresBlobStore>((*shared)->pool());
  options.store = *std::move(shared);
  return absl::OkStatus();
#else
  (void)connections;
  return absl::FailedPreconditionError(
      "this lsqsurfd was built without PostgreSQL (LSQSURF_WITH_POSTGRESQL=OFF): use --store sqlite, or a build "
      "with it");
#endif
}

// The command line: the job service's options, and the server's own.
struct ServerFlags {
  std::string listen = "127.0.0.1:50051";
  std::string store = "sqlite", blob_dir, metrics_listen, http_listen;
  int store_connections = 8;
  bool parameter_reference = false, limits_reference = false;
  lsqsurf::server::TlsFiles tls;
  bool plaintext = false;
  std::string auth_tokens;
  // The limits' flags (server/limits.h), one per row, in its unit.
  std::vector<double> limits;
  std::vector<CLI::Option*> limit_options;
  lsqsurf::server::StreamLimits streams;
  double stream_idle_seconds = 0;  // Set from StreamLimits::idle, whose default it shows.
  int max_streams_per_connection = 100;
  int max_threads = 64;
  lsqsurf::server::HttpLimits http;
  int64_t http_max_head_kib = 0;  // Set from HttpLimits::connection_memory_bytes, whose default it shows.
  std::vector<std::string> http_hosts;
};

// `lsqsurfd tokens add|list|revoke`: edits a token file.
struct TokenCommand {
  CLI::App* add = nullptr;
  CLI::App* list = nullptr;
  CLI::App* revoke = nullptr;
  std::string file, name, role = "user";
  lsqsurf::server::TokenEntry quotas;
};

void DefineTokenCommand(CLI::App& app, TokenCommand& command) {
  CLI::App* tokens = app.add_subcommand("tokens", "make, list and revoke the tokens of a --auth-tokens file");
  tokens->require_subcommand(1);
  command.add = tokens->add_subcommand(
      "add", "make a token for NAME, add its salted hash to FILE (made if missing) and print the token, once");
  command.list = tokens->add_subcommand("list", "list the names, roles and quotas in FILE");
  command.revoke = tokens->add_subcommand("revoke", "remove NAME's token from FILE");
  for (CLI::App* sub : {command.add, command.list, command.revoke}) {
    sub->add_option("file", command.file, "the token file")->required();
  }
  for (CLI::App* sub : {command.add, command.revoke}) {
    sub->add_option("name", command.name, "the token's holder: letters, digits, _.@- (at most 64)")->required();
  }
  command.add->add_option("--role", command.role, "user: its own jobs only; admin: every job")
      ->capture_default_str()
      ->check(CLI::IsMember({"user", "admin"}));
  command.add->add_option("--max-jobs", command.quotas.max_jobs, "jobs queued or running at once (0: no limit)")
      ->check(CLI::Range(0, 1'000'000));
  command.add
      ->add_option("--max-stored-mib", command.quotas.max_stored_mib,
                   "MiB its jobs may keep, uploads and results (0: no limit)")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 30));
  command.add->add_option("--max-upload-mib", command.quotas.max_upload_mib, "largest upload, MiB (0: the server's)")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 20));
}

int RunTokenCommand(const TokenCommand& command) {
  namespace server = lsqsurf::server;
  if (command.add->parsed()) {
    server::TokenEntry entry = command.quotas;
    entry.name = command.name;
    entry.role = *server::ParseRole(command.role);
    auto token = server::AddToken(command.file, entry);
    if (!token.ok()) {
      std::fprintf(stderr, "lsqsurfd tokens add: %s\n", std::string(token.status().message()).c_str());
      return 1;
    }
    std::printf("%s\n", token->c_str());
    std::fprintf(stderr, "added %s's token (%s) to %s; it is shown only now: keep it where its user can read it\n",
                 entry.name.c_str(), server::RoleName(entry.role), command.file.c_str());
    return 0;
  }
  if (command.revoke->parsed()) {
    if (absl::Status s = server::RevokeToken(command.file, command.name); !s.ok()) {
      std::fprintf(stderr, "lsqsurfd tokens revoke: %s\n", std::string(s.message()).c_str());
      return 1;
    }
    std::fprintf(stderr, "revoked %s's token; a running lsqsurfd refuses it after SIGHUP\n", command.name.c_str());
    return 0;
  }
  auto entries = server::ReadTokenFile(command.file);
  if (!entries.ok()) {
    std::fprintf(stderr, "lsqsurfd tokens list: %s\n", std::string(entries.status().message()).c_str());
    return 1;
  }
  std::printf("%-24s %-6s %9s %15s %15s\n", "NAME", "ROLE", "MAX_JOBS", "MAX_STORED_MIB", "MAX_UPLOAD_MIB");
  for (const auto& e : *entries) {
    std::printf("%-24s %-6s %9d %15lld %15lld\n", e.name.c_str(), server::RoleName(e.role), e.max_jobs,
                static_cast<long long>(e.max_stored_mib), static_cast<long long>(e.max_upload_mib));
  }
  return 0;
}

// One flag per row of the limits table, its default from `options`.
void DefineLimitFlags(CLI::App& app, ServerFlags& flags, const lsqsurf::jobs::JobServiceOptions& options) {
  const auto rows = lsqsurf::server::ServerLimits();
  flags.limits.resize(rows.size());
  for (size_t i = 0; i < rows.size(); ++i) {
    const lsqsurf::server::ServerLimit& row = rows[i];
    flags.limits[i] = row.get(options);
    CLI::Option* option = app.add_option(lsqsurf::core::StrCat("--", row.flag), flags.limits[i], std::string(row.help));
    option->default_str(lsqsurf::server::LimitText(row, flags.limits[i]))
        ->check(CLI::Range(row.min, row.max).description(""));
    if (row.integer) {
      option->check(CLI::Validator(
          [](const std::string& text) {
            char* end = nullptr;
            const double value = std::strtod(text.c_str(), &end);
            const bool whole = end != text.c_str() && *end == '\0' && value == std::floor(value);
            return whole ? std::string() : std::string("a whole number is expected, not ") + text;
          },
          ""));
    }
    // Its range as the table writes it (CLI11 would print the doubles it is checked in).
    option->type_name(lsqsurf::core::StrCat(row.integer ? "INT" : "NUMBER", " in [",
                                            lsqsurf::server::LimitText(row, row.min), ", ",
                                            lsqsurf::server::LimitText(row, row.max), "]"));
    flags.limit_options.push_back(option);
  }
}

void DefineFlags(CLI::App& app, ServerFlags& flags, lsqsurf::jobs::JobServiceOptions& options) {
  app.add_option("--listen", flags.listen, "HOST:PORT to listen on; port 0 picks a free port")->capture_default_str();
  DefineLimitFlags(app, flags, options);
  app.add_option("--data-dir", options.data_dir, "where jobs, inputs and results are kept")->capture_default_str();
  app.add_option("--max-uploads", flags.streams.max_uploads,
                 "SubmitJob streams open at once (a named user holds at most half); more are refused")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  app.add_option("--max-downloads", flags.streams.max_downloads, "FetchResult streams open at once (half per user)")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  app.add_option("--max-watches", flags.streams.max_watches, "WatchJob streams open at once (half per user)")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000000));
  app.add_option("--max-reflection-streams", flags.streams.max_reflection,
                 "server reflection streams open at once (they need no token)")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  app.add_option("--stream-idle-seconds", flags.stream_idle_seconds,
                 "an upload that sends nothing, a download whose client reads nothing or a reflection stream that "
                 "asks nothing for this long is cancelled")
      ->capture_default_str()
      ->check(CLI::Range(1.0, 86400.0));
  app.add_option("--max-streams-per-connection", flags.max_streams_per_connection,
                 "concurrent calls one client connection may have open")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  app.add_option("--max-threads", flags.max_threads,
                 "threads gRPC may run the short calls on (streams hold none); past it calls are refused")
      ->capture_default_str()
      ->check(CLI::Range(4, 10000));
  app.add_option("--store", flags.store,
                 "where jobs are kept: 'sqlite' (a file in the data directory, one server) or a "
                 "postgresql://user@host:port/database URL that several servers share (a password is better "
                 "kept in PGPASSWORD or ~/.pgpass than in the URL)")
      ->capture_default_str();
  app.add_option("--blob-dir", flags.blob_dir,
                 "where uploads and results are kept; default: the data directory with --store sqlite, the "
                 "database with --store postgresql:// (give a shared volume here to keep them out of it)");
  app.add_option("--name", options.name, "this server's name among those sharing a store (default: host name)");
  // Hidden: only the mixed-build check (scripts/netns-replicas.sh) makes a server claim tiles as
  // one of another build would.
  app.add_option("--tile-format", options.tile_format, "tests of mixed builds: the tile format to claim in")->group("");
  app.add_option("--store-connections", flags.store_connections, "connections to a PostgreSQL store")
      ->capture_default_str()
      ->check(CLI::Range(2, 64));
  app.add_option("--metrics-listen", flags.metrics_listen,
                 "HOST:PORT on which to serve Prometheus metrics at /metrics, plain HTTP under the --http-* bounds "
                 "and Host check (off when not given)");
  app.add_option("--http-listen", flags.http_listen,
                 "HOST:PORT on which to serve the job page and its JSON API (off when not given; HTTPS with "
                 "--tls-cert; the same tokens; port 0 picks a free port, printed as 'http on URL')");
  app.add_option("--tls-cert", flags.tls.cert, "PEM certificate chain to serve TLS with (read again on SIGHUP)");
  app.add_option("--tls-key", flags.tls.key, "PEM private key of --tls-cert");
  app.add_option("--tls-client-ca", flags.tls.client_ca,
                 "PEM CA bundle: clients must present a certificate it signed (mutual TLS)");
  app.add_flag("--plaintext", flags.plaintext,
               "serve without TLS on a non-loopback address (e.g. behind a proxy that terminates TLS); "
               "loopback addresses are served in plaintext without it");
  app.add_option("--auth-tokens", flags.auth_tokens,
                 "token file (`lsqsurfd tokens add`): every call then needs a token, and users see only their "
                 "own jobs (read again on SIGHUP)");
  app.set_config("--config", "", "read options from this TOML/INI file");
  app.add_flag("--limits-reference", flags.limits_reference,
               "print the job service's limits (flags, defaults, ranges) as Markdown, then exit");
  app.add_flag("--parameter-reference", flags.parameter_reference,
               "print every method's parameters (and the view options) as Markdown, then exit");
}

// What one client, and all of them, may hold of the --http-listen port.
void DefineHttpFlags(CLI::App& app, ServerFlags& flags) {
  lsqsurf::server::HttpLimits& limits = flags.http;
  flags.http_max_head_kib = static_cast<int64_t>(limits.connection_memory_bytes >> 10);
  app.add_option("--http-host", flags.http_hosts,
                 "a host name the job page answers to (repeatable); besides these only IP addresses and "
                 "localhost are, so that a web page cannot rebind its own name to this server");
  app.add_option("--http-max-head-kib", flags.http_max_head_kib,
                 "KiB that one HTTP request's line and headers may take (more: 431, connection closed)")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{8}, int64_t{1024}));
  app.add_option("--http-max-connections", limits.max_connections, "HTTP connections open at once")
      ->capture_default_str()
      ->check(CLI::Range(1u, 100000u));
  app.add_option("--http-max-connections-per-peer", limits.max_connections_per_peer,
                 "HTTP connections open at once from one address")
      ->capture_default_str()
      ->check(CLI::Range(1u, 100000u));
  app.add_option("--http-head-seconds", limits.head_seconds,
                 "seconds from an HTTP connection's start (or its previous answer) by which a request's whole "
                 "head must have come, however it trickles")
      ->capture_default_str()
      ->check(CLI::Range(1u, 3600u));
  app.add_option("--http-idle-seconds", limits.idle_seconds,
                 "seconds without a byte either way after which an HTTP connection is closed")
      ->capture_default_str()
      ->check(CLI::Range(1u, 3600u));
  app.add_option("--http-max-requests-per-connection", limits.max_requests_per_connection,
                 "requests on one kept-alive HTTP connection")
      ->capture_default_str()
      ->check(CLI::Range(1u, 100000u));
  app.add_option("--http-threads", limits.threads, "HTTP event loops (each answers its connections' requests)")
      ->capture_default_str()
      ->check(CLI::Range(1u, 64u));
}

// What lsqsurfd serves with: TLS (`tls` set) or plaintext, and the tokens it takes (null: none).
struct Security {
  std::unique_ptr<lsqsurf::server::ServerTls> tls;
  std::shared_ptr<grpc::ServerCredentials> credentials;
  std::unique_ptr<lsqsurf::server::TokenTable> tokens;
};

absl::StatusOr<Security> OpenSecurity(const ServerFlags& flags, const std::string& data_dir) {
  namespace server = lsqsurf::server;
  Security security;
  if (!flags.auth_tokens.empty()) {
    auto tokens = server::TokenTable::Load(flags.auth_tokens);
    if (!tokens.ok()) return tokens.status();
    security.tokens = *std::move(tokens);
  }
  const bool loopback = lsqsurf::core::IsLoopback(flags.listen);
  if (flags.tls.cert.empty() != flags.tls.key.empty()) {
    return absl::InvalidArgumentError("--tls-cert and --tls-key go together");
  }
  if (flags.tls.cert.empty()) {
    if (!flags.tls.client_ca.empty())
      return absl::InvalidArgumentError("--tls-client-ca needs --tls-cert and --tls-key");
    if (!loopback && !flags.plaintext) {
      return absl::InvalidArgumentError(
          lsqsurf::core::StrCat("lsqsurfd would listen on ", flags.listen,
                                " without TLS: give --tls-cert and --tls-key, or --plaintext "
                                "(e.g. behind a proxy that terminates TLS)"));
    }
    if (!loopback) {
      spdlog::warn("serving plaintext on {}: tokens, uploads and results cross the network unencrypted", flags.listen);
    }
    security.credentials = grpc::InsecureServerCredentials();
    return security;
  }
  auto tls = server::ServerTls::Open(flags.tls, (std::filesystem::path(data_dir) / "tls").string());
  if (!tls.ok()) return tls.status();
  security.tls = *std::move(tls);
  security.credentials = security.tls->credentials();
  spdlog::info("TLS{}: {}", flags.tls.client_ca.empty() ? "" : " with client certificates",
               security.tls->description());
  return security;
}

// SIGHUP: the token file and the certificate are read again; a bad one is refused and logged,
// and the one in use stays.
void Reload(Security& security) {
  if (security.tokens != nullptr) {
    if (auto count = security.tokens->Reload(); count.ok()) {
      spdlog::info("tokens reloaded: {} in {}", *count, security.tokens->path());
    } else {
      spdlog::error("tokens not reloaded, the previous ones stay: {}", count.status().message());
    }
  }
  if (security.tls != nullptr) {
    if (auto description = security.tls->Reload(); description.ok()) {
      spdlog::info("certificate reloaded: {}", *description);
    } else {
      spdlog::error("certificate not reloaded, the previous one stays: {}", description.status().message());
    }
  }
}

// The flags given in user units (MiB, seconds, days) into the options' own.
void ApplyUnits(ServerFlags& flags, lsqsurf::jobs::JobServiceOptions& options) {
  const auto rows = lsqsurf::server::ServerLimits();
  for (size_t i = 0; i < rows.size(); ++i) {
    if (flags.limit_options[i]->count() > 0) rows[i].set(options, flags.limits[i]);
  }
  flags.streams.idle = std::chrono::milliseconds(static_cast<int64_t>(flags.stream_idle_seconds * 1000));
}

}  // namespace

// The job page (--http-listen) on the gRPC server's in-process channel, under the gRPC port's
// rules: TLS with the same files, and plaintext off loopback only with --plaintext.
// The HTTP front's settings from the flags: the job page's, which the metrics port shares.
lsqsurf::server::HttpFrontOptions HttpOptions(const ServerFlags& flags) {
  lsqsurf::server::HttpFrontOptions options;
  options.listen = flags.http_listen;
  options.tls_cert_path = flags.tls.cert;
  options.tls_key_path = flags.tls.key;
  options.host_names = flags.http_hosts;
  options.limits = flags.http;
  options.limits.connection_memory_bytes = static_cast<size_t>(flags.http_max_head_kib) << 10;
  return options;
}

absl::StatusOr<std::unique_ptr<lsqsurf::server::HttpGateway>> StartHttp(const ServerFlags& flags,
                                                                        lsqsurf::server::Server& server) {
  if (flags.tls.cert.empty() && !flags.plaintext && !lsqsurf::core::IsLoopback(flags.http_listen)) {
    return absl::InvalidArgumentError(lsqsurf::core::StrCat(
        "--http-listen ", flags.http_listen,
        " is not a loopback address: give --tls-cert and --tls-key (HTTPS), or --plaintext behind a proxy"));
  }
  if (!flags.tls.client_ca.empty()) {
    return absl::InvalidArgumentError("--http-listen does not take client certificates (--tls-client-ca); use tokens");
  }
  return lsqsurf::server::HttpGateway::Start(server.InProcessChannel(), HttpOptions(flags));
}

int main(int argc, char** argv) {
  CLI::App app{"lsqsurfd: surface reconstruction server"};
  ServerFlags flags;
  lsqsurf::jobs::JobServiceOptions options;
  options.data_dir = "lsqsurf-data";
  flags.stream_idle_seconds = std::chrono::duration<double>(flags.streams.idle).count();
  DefineFlags(app, flags, options);
  DefineHttpFlags(app, flags);
  TokenCommand token_command;
  DefineTokenCommand(app, token_command);
  CLI11_PARSE(app, argc, argv);
  if (!app.get_subcommands().empty()) return RunTokenCommand(token_command);
  if (flags.parameter_reference || flags.limits_reference) {
    const std::string reference =
        flags.parameter_reference ? lsqsurf::jobs::ParameterReference() : lsqsurf::server::LimitsReference(options);
    std::fputs(reference.c_str(), stdout);
    return 0;
  }
  ApplyUnits(flags, options);

  // Logs go to stderr; stdout carries only the "listening on" line that scripts wait for.
  spdlog::set_default_logger(spdlog::stderr_color_mt("lsqsurfd"));
  spdlog::set_pattern("%Y-%m-%d %H:%M:%S.%e %^%l%$ %v");

  // Block the shutdown signals in every thread; one thread waits for them below.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGHUP);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  auto security = OpenSecurity(flags, options.data_dir);
  if (!security.ok()) {
    spdlog::critical("cannot start: {}", security.status().message());
    return 1;
  }

  if (absl::Status s = OpenStores(flags.store, flags.blob_dir, flags.store_connections, options); !s.ok()) {
    spdlog::critical("cannot start: {}", s.ToString());
    return 1;
  }
  std::shared_ptr<lsqsurf::server::Metrics> metrics;
  if (!flags.metrics_listen.empty()) {
    lsqsurf::server::HttpFrontOptions metrics_options = HttpOptions(flags);
    metrics_options.listen = flags.metrics_listen;
    metrics_options.tls_cert_path.clear();  // Plain HTTP, as Prometheus scrapes by default.
    metrics_options.tls_key_path.clear();
    metrics_options.limits.threads = 1;
    auto started = lsqsurf::server::Metrics::Start(metrics_options);
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
  lsqsurf::server::ServerOptions server_options;
  server_options.listen = flags.listen;
  server_options.credentials = security->credentials;
  server_options.tokens = security->tokens.get();
  server_options.calls = metrics.get();
  server_options.streams = flags.streams;
  server_options.max_streams_per_connection = flags.max_streams_per_connection;
  server_options.max_threads = flags.max_threads;
  auto server = lsqsurf::server::Server::Start(**jobs, server_options);
  if (!server.ok()) {
    spdlog::critical("cannot start: {}", server.status().message());
    return 1;
  }
  std::unique_ptr<lsqsurf::server::HttpGateway> http;
  if (!flags.http_listen.empty()) {
    auto started = StartHttp(flags, **server);
    if (!started.ok()) {
      spdlog::critical("cannot start: {}", started.status().message());
      return 1;
    }
    http = *std::move(started);
  }
  std::printf("listening on %s\n", (*server)->address().c_str());
  if (http != nullptr) std::printf("http on %s\n", http->address().c_str());
  std::fflush(stdout);
  spdlog::info("serving on {}", (*server)->address());

  std::thread waiter([&] {
    int signal = 0;
    while (sigwait(&signals, &signal) == 0 && signal == SIGHUP) Reload(*security);
    spdlog::info("signal {} received: shutting down", signal);
    if (http != nullptr) http->Stop();
    (*server)->Drain();
    // Nothing is lost past this point. gRPC's teardown has been seen to hang for good after its
    // threads ran out (in the TLS credentials' destructor): the process then ends regardless.
    std::thread([] {
      std::this_thread::sleep_for(kTeardownGrace);
      spdlog::warn("the server's teardown did not end within {} s; exiting now", kTeardownGrace.count());
      spdlog::default_logger()->flush();
      std::_Exit(0);
    }).detach();
    (*server)->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(3));
  });
  (*server)->Wait();
  waiter.join();
  if (metrics != nullptr) metrics->Stop();
  spdlog::info("stopped");
  return 0;
}
