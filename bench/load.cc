// lsqsurf-load — drives a server (or a balancer in front of several) with concurrent clients and
// reports throughput, per-call latency percentiles and every refusal by status code.
//
//   lsqsurf-load --server 127.0.0.1:50051 --cloud bunny.ply --points 100000 --method iamls --jobs 30
//       --submitters 3 --pollers 4
//   lsqsurf-load --cloud spot.ply --points 2000 --large-points 200000 --large-every 5 --bad-every 7
//       --cancel-every 6 --duration-s 1800 --submitters 8 --accepted accepted.txt
//   lsqsurf-load --verify accepted.txt
//
// `submitters` clients each upload a job, follow it to its end (WatchJob) and fetch and decode
// its result, then submit the next: until `jobs` have been submitted, or for `duration-s`. Every
// `large-every`-th upload is a large cloud, every `bad-every`-th a truncated one (which must be
// refused with INVALID_ARGUMENT), every `cancel-every`-th accepted job is cancelled at once.
// Meanwhile `pollers` clients call GetJob on the jobs submitted so far. A server that goes away
// (UNAVAILABLE) is waited for: calls are retried while the run lasts. Accepted job ids are
// appended to --accepted; --verify follows every id of such a file to its end and checks that
// each succeeded job's results decode. Every loop is bounded by the job count and by time.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <map>
#include <mutex>
#include <random>
#include <thread>

#include "client/client.h"
#include "worker/core/sampling.h"
#include "worker/core/status.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace v1 = lsqsurf::v1;
namespace client = lsqsurf::client;

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const size_t at = std::min(values.size() - 1, static_cast<size_t>(p / 100.0 * static_cast<double>(values.size())));
  return values[at];
}

struct LoadOptions {
  std::string server = "127.0.0.1:50051";
  std::string cloud;
  int64_t points = 0;  // > 0: `cloud` is a mesh, sampled with this many points.
  std::string method = "iamls";
  std::vector<std::string> params;
  int jobs = 30;  // 0 with --duration-s: as many as fit.
  int submitters = 3;
  int pollers = 4;
  int poll_interval_ms = 50;
  double timeout_s = 3600;  // Stop submitting after this long.
  double duration_s = 0;    // > 0: submit for this long, then finish the jobs being followed.
  double drain_s = 600;     // After the submitting ends: how long followed jobs may take to end.
  int64_t large_points = 0;
  int large_every = 0, bad_every = 0, cancel_every = 0;
  std::string accepted;      // File the accepted job ids are appended to.
  std::string verify;        // File of job ids to check instead of making load.
  std::string token;         // From LSQSURF_TOKEN.
  std::string tls_ca;        // PEM file: talk TLS, trusting these certificates.
  bool submit_only = false;  // Neither follow nor fetch: upload, and cancel as asked.

  client::ConnectOptions Connect(std::chrono::milliseconds unary_deadline) const {
    client::ConnectOptions connect;
    connect.token = token;
    connect.unary_deadline = unary_deadline;
    if (!tls_ca.empty()) connect.ca_pem = lsqsurf::io::ReadFileBytes(tls_ca).value_or("");
    return connect;
  }
};

// Latencies by rpc, outcomes by name and count; shared by every client thread.
struct Tally {
  std::mutex mutex;
  std::vector<std::string> ids;  // Jobs accepted so far.
  std::vector<double> job_seconds;
  std::map<std::string, std::vector<double>> rpc_ms;
  std::map<std::string, int> outcomes;
  std::ofstream accepted;

  void Count(const std::string& what, int n = 1) {
    std::lock_guard lock(mutex);
    outcomes[what] += n;
  }
  void Refused(const char* rpc, const absl::Status& status) {
    Count(std::string(rpc) + " " + absl::StatusCodeToString(status.code()));
  }
  void Took(const char* rpc, Clock::time_point start) {
    const double ms = Seconds(Clock::now() - start) * 1000;
    std::lock_guard lock(mutex);
    rpc_ms[rpc].push_back(ms);
  }
  void Accepted(const std::string& id) {
    std::lock_guard lock(mutex);
    ids.push_back(id);
    if (accepted.is_open()) accepted << id << '\n' << std::flush;
  }
  int count(const std::string& what) {
    std::lock_guard lock(mutex);
    auto it = outcomes.find(what);
    return it == outcomes.end() ? 0 : it->second;
  }
};

bool Retryable(const absl::Status& s) {
  return s.code() == absl::StatusCode::kUnavailable || s.code() == absl::StatusCode::kAborted ||
         s.code() == absl::StatusCode::kCancelled;
}

// Fetches every result of a succeeded job and decodes the Draco ones (a mesh, else a point
// set); false when one does not decode.
bool ResultsDecode(client::Client& c, const v1::Job& job, Tally& tally) {
  for (const std::string& name : job.results()) {
    const auto start = Clock::now();
    auto bytes = c.Fetch(job.id(), name);
    if (!bytes.ok()) {
      tally.Refused("FetchResult", bytes.status());
      if (Retryable(bytes.status())) continue;  // The server went away; not the result's fault.
      return false;
    }
    tally.Took("FetchResult", start);
    if (name.size() < 4 || name.substr(name.size() - 4) != ".drc") {
      if (bytes->empty()) return false;
      continue;
    }
    if (!lsqsurf::io::DecodeDracoMesh(*bytes).ok() && !lsqsurf::io::DecodeDracoPointCloud(*bytes).ok()) return false;
  }
  return true;
}

// Follows a job to its end through server restarts, until `deadline`; the last job seen.
absl::StatusOr<v1::Job> FollowToEnd(client::Client& c, const std::string& id, Clock::time_point deadline,
                                    Tally& tally) {
  for (;;) {
    auto done = c.Watch(id);
    if (done.ok() || !Retryable(done.status()) || Clock::now() > deadline) return done;
    tally.Refused("WatchJob", done.status());
    std::this_thread::sleep_for(std::chrono::milliseconds(250));
  }
}

// The uploads one client cycles through.
struct Inputs {
  v1::JobSpec spec;
  std::string small, large, bad;
};

void Submitter(const LoadOptions& o, const Inputs& in, std::atomic<int>& next, Clock::time_point stop_submitting,
               Tally& tally) {
  client::Client c(o.server, o.Connect(std::chrono::seconds(30)));
  const auto drain_deadline = stop_submitting + std::chrono::milliseconds(static_cast<int64_t>(o.drain_s * 1000));
  for (;;) {
    const int n = next.fetch_add(1);
    if ((o.jobs > 0 && n >= o.jobs) || Clock::now() >= stop_submitting) return;
    const bool bad = o.bad_every > 0 && n % o.bad_every == o.bad_every - 1;
    const bool large = !bad && o.large_every > 0 && n % o.large_every == o.large_every - 1;
    const auto start = Clock::now();
    auto job = c.Submit(in.spec, bad ? in.bad : large ? in.large : in.small);
    if (bad) {
      tally.Count(job.ok() ? "bad input accepted"
                           : "bad input refused " + absl::StatusCodeToString(job.status().code()));
      continue;
    }
    if (!job.ok()) {
      tally.Refused("SubmitJob", job.status());
      // A full queue or a server that went away: back off a little before the next try.
      if (Retryable(job.status()) || job.status().code() == absl::StatusCode::kResourceExhausted) {
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
      }
      continue;
    }
    tally.Took("SubmitJob", start);
    tally.Accepted(job->id());
    if (o.cancel_every > 0 && n % o.cancel_every == o.cancel_every - 1) {
      const auto cancel_start = Clock::now();
      auto cancelled = c.Cancel(job->id());
      if (cancelled.ok()) {
        tally.Took("CancelJob", cancel_start);
      } else {
        tally.Refused("CancelJob", cancelled.status());
      }
    }
    if (o.submit_only) continue;
    auto done = FollowToEnd(c, job->id(), drain_deadline, tally);
    if (!done.ok()) {
      tally.Refused("WatchJob", done.status());
      continue;
    }
    tally.Count(std::string("job ") + client::StateName(done->state()));
    if (done->state() != v1::JOB_STATE_SUCCEEDED) continue;
    {
      std::lock_guard lock(tally.mutex);
      tally.job_seconds.push_back(Seconds(Clock::now() - start));
    }
    if (!ResultsDecode(c, *done, tally)) tally.Count("corrupt result");
  }
}

void Poller(const LoadOptions& o, const std::atomic<bool>& stop, Tally& tally, unsigned seed) {
  client::Client c(o.server, o.Connect(std::chrono::seconds(30)));
  std::mt19937 rng(seed);
  while (!stop) {
    std::string id;
    {
      std::lock_guard lock(tally.mutex);
      if (!tally.ids.empty()) id = tally.ids[rng() % tally.ids.size()];
    }
    if (!id.empty()) {
      const auto start = Clock::now();
      auto job = c.Get(id);
      if (job.ok()) {
        tally.Took("GetJob", start);
      } else {
        tally.Refused("GetJob", job.status());
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(o.poll_interval_ms));
  }
}

// --verify: every listed job must have ended and every succeeded one's results must decode.
int Verify(const LoadOptions& o) {
  std::ifstream in(o.verify);
  if (!in) {
    std::fprintf(stderr, "lsqsurf-load: cannot read %s\n", o.verify.c_str());
    return 2;
  }
  std::vector<std::string> ids;
  for (std::string id; std::getline(in, id);) {
    if (!id.empty()) ids.push_back(id);
  }
  client::Client c(o.server, o.Connect(std::chrono::milliseconds(0)));
  Tally tally;
  const auto deadline = Clock::now() + std::chrono::milliseconds(static_cast<int64_t>(o.drain_s * 1000));
  int lost = 0, unfinished = 0, corrupt = 0;
  std::map<std::string, int> states;
  for (const std::string& id : ids) {
    auto job = FollowToEnd(c, id, deadline, tally);
    if (!job.ok()) {
      ++(job.status().code() == absl::StatusCode::kNotFound ? lost : unfinished);
      std::fprintf(stderr, "job %s: %s\n", id.c_str(), job.status().ToString().c_str());
      continue;
    }
    ++states[client::StateName(job->state())];
    if (job->state() == v1::JOB_STATE_SUCCEEDED && !ResultsDecode(c, *job, tally)) {
      ++corrupt;
      std::fprintf(stderr, "job %s: a result does not decode\n", id.c_str());
    }
  }
  std::printf("verified %zu accepted jobs:", ids.size());
  for (const auto& [state, n] : states) std::printf(" %s %d,", state.c_str(), n);
  std::printf(" lost %d, unfinished %d, corrupt results %d\n", lost, unfinished, corrupt);
  return lost + unfinished + corrupt == 0 ? 0 : 1;
}

absl::StatusOr<Inputs> MakeInputs(const LoadOptions& o) {
  const auto sample = [&](int64_t points) -> absl::StatusOr<lsqsurf::core::PointCloud> {
    if (points <= 0) return lsqsurf::io::ReadPointCloudFile(o.cloud);
    auto mesh = lsqsurf::io::ReadMeshFile(o.cloud);
    if (!mesh.ok()) return mesh.status();
    return lsqsurf::core::SampleCloud(*mesh, static_cast<size_t>(points), /*seed=*/1);
  };
  Inputs in;
  auto small = sample(o.points);
  if (!small.ok()) return small.status();
  auto bytes = lsqsurf::io::EncodeDracoPointCloud(*small, {});
  if (!bytes.ok()) return bytes.status();
  in.small = *std::move(bytes);
  in.bad = in.small.substr(0, in.small.size() / 2);  // Truncated: must be refused.
  if (o.large_points > 0) {
    auto large = sample(o.large_points);
    if (!large.ok()) return large.status();
    auto large_bytes = lsqsurf::io::EncodeDracoPointCloud(*large, {});
    if (!large_bytes.ok()) return large_bytes.status();
    in.large = *std::move(large_bytes);
  } else {
    in.large = in.small;
  }
  LSQSURF_RETURN_IF_ERROR(client::SetMethod(&in.spec, o.method));
  for (const auto& p : o.params) LSQSURF_RETURN_IF_ERROR(client::SetParamAssignment(&in.spec, p));
  return in;
}

void DefineOptions(CLI::App& app, LoadOptions& o) {
  app.add_option("--server", o.server, "HOST:PORT of the server or balancer")->capture_default_str();
  app.add_option("--cloud", o.cloud, "point cloud every job uploads (PLY, OBJ, XYZ, Draco)");
  app.add_option("--points", o.points, "read --cloud as a mesh and upload this many points sampled on it")
      ->check(CLI::Range(int64_t{16}, int64_t{100'000'000}));
  app.add_option("--method", o.method, "method of every job")->capture_default_str();
  app.add_option("--param", o.params, "NAME=VALUE for the method (repeatable)");
  app.add_option("--jobs", o.jobs, "jobs to submit (0 with --duration-s: no limit)")
      ->capture_default_str()
      ->check(CLI::Range(0, 1000000));
  app.add_option("--submitters", o.submitters, "clients submitting and following jobs")
      ->capture_default_str()
      ->check(CLI::Range(1, 256));
  app.add_option("--pollers", o.pollers, "clients calling GetJob")->capture_default_str()->check(CLI::Range(0, 256));
  app.add_option("--poll-interval-ms", o.poll_interval_ms, "pause between one poller's calls")
      ->capture_default_str()
      ->check(CLI::Range(0, 60000));
  app.add_option("--timeout-s", o.timeout_s, "stop submitting after this long")->capture_default_str();
  app.add_option("--duration-s", o.duration_s, "submit for this long, then let the followed jobs end")
      ->check(CLI::Range(0.0, 7 * 86400.0));
  app.add_option("--drain-s", o.drain_s, "how long followed (or verified) jobs may take to end")->capture_default_str();
  app.add_option("--large-points", o.large_points, "points of the large cloud (sampled like --points)")
      ->check(CLI::Range(int64_t{16}, int64_t{100'000'000}));
  app.add_option("--large-every", o.large_every, "every Nth upload is the large cloud")->check(CLI::Range(0, 1000));
  app.add_option("--bad-every", o.bad_every, "every Nth upload is truncated (must be refused)")
      ->check(CLI::Range(0, 1000));
  app.add_option("--cancel-every", o.cancel_every, "every Nth accepted job is cancelled at once")
      ->check(CLI::Range(0, 1000));
  app.add_option("--accepted", o.accepted, "append the ids of accepted jobs to this file");
  app.add_option("--tls-ca", o.tls_ca, "talk TLS to the server, trusting the certificates of this PEM file");
  app.add_flag("--submit-only", o.submit_only, "upload (and cancel as asked) without following the jobs");
  app.add_option("--verify", o.verify, "follow every job id of this file to its end and decode its results; no load");
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf-load: concurrent jobs and calls against a server, with latencies and refusals"};
  LoadOptions o;
  DefineOptions(app, o);
  CLI11_PARSE(app, argc, argv);
  if (const char* token = std::getenv("LSQSURF_TOKEN")) o.token = token;
  if (!o.verify.empty()) return Verify(o);
  if (o.cloud.empty()) {
    std::fprintf(stderr, "lsqsurf-load: --cloud is required\n");
    return 2;
  }
  auto inputs = MakeInputs(o);
  if (!inputs.ok()) {
    std::fprintf(stderr, "lsqsurf-load: %s\n", std::string(inputs.status().message()).c_str());
    return 2;
  }
  Tally tally;
  if (!o.accepted.empty()) tally.accepted.open(o.accepted, std::ios::app);
  std::atomic<int> next{0};
  std::atomic<bool> stop{false};
  const auto start = Clock::now();
  const double submit_s = o.duration_s > 0 ? o.duration_s : o.timeout_s;
  const auto stop_submitting = start + std::chrono::milliseconds(static_cast<int64_t>(submit_s * 1000));
  std::vector<std::thread> pollers, submitters;
  for (int i = 0; i < o.pollers; ++i) pollers.emplace_back([&, i] { Poller(o, stop, tally, 17u + i); });
  for (int i = 0; i < o.submitters; ++i) {
    submitters.emplace_back([&] { Submitter(o, *inputs, next, stop_submitting, tally); });
  }
  for (auto& t : submitters) t.join();
  const double wall = Seconds(Clock::now() - start);
  stop = true;
  for (auto& t : pollers) t.join();

  std::printf("server %s, %s, %d submitters, %d pollers every %d ms\n", o.server.c_str(), o.method.c_str(),
              o.submitters, o.pollers, o.poll_interval_ms);
  std::printf("wall %.1f s, %zu jobs accepted, %zu succeeded: %.2f jobs/min\n", wall, tally.ids.size(),
              tally.job_seconds.size(), 60.0 * static_cast<double>(tally.job_seconds.size()) / wall);
  std::printf("job submit-to-end s: p50 %.2f  p90 %.2f  max %.2f\n", Percentile(tally.job_seconds, 50),
              Percentile(tally.job_seconds, 90), Percentile(tally.job_seconds, 100));
  for (const auto& [rpc, ms] : tally.rpc_ms) {
    std::printf("%-12s ms (%zu calls): p50 %.2f  p90 %.2f  p99 %.2f  max %.2f\n", rpc.c_str(), ms.size(),
                Percentile(ms, 50), Percentile(ms, 90), Percentile(ms, 99), Percentile(ms, 100));
  }
  for (const auto& [what, n] : tally.outcomes) std::printf("  %-36s %d\n", what.c_str(), n);
  // A hang (a call past its deadline), a corrupt result or an accepted bad input fails the run;
  // without the mixed load, so does any job that did not succeed.
  const bool mixed = o.bad_every > 0 || o.cancel_every > 0 || o.duration_s > 0 || o.submit_only;
  const int hung = tally.count("GetJob DEADLINE_EXCEEDED") + tally.count("CancelJob DEADLINE_EXCEEDED");
  if (hung > 0 || tally.count("corrupt result") > 0 || tally.count("bad input accepted") > 0) return 1;
  if (!mixed && tally.job_seconds.size() != static_cast<size_t>(o.jobs)) return 1;
  return 0;
}
