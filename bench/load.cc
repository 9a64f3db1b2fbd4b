// lsqsurf-load — drives a server (or a balancer in front of several) with concurrent jobs and
// status queries, and reports throughput and per-call latency.
//
//   lsqsurf-load --server 127.0.0.1:50051 --cloud bunny.ply --points 100000 --method iamls --jobs 30
//       --submitters 3 --pollers 4
//
// `submitters` clients each upload a job and follow it to its end, then submit the next, until
// `jobs` have been submitted; meanwhile `pollers` clients call GetJob on the jobs submitted so
// far, one call every `poll-interval-ms` each. Every loop is bounded by the job count and by
// --timeout-s.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <map>
#include <mutex>
#include <random>
#include <thread>

#include "client/client.h"
#include "worker/core/sampling.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace v1 = lsqsurf::v1;

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const size_t at = std::min(values.size() - 1, static_cast<size_t>(p / 100.0 * static_cast<double>(values.size())));
  return values[at];
}

struct Tally {
  std::mutex mutex;
  std::vector<std::string> ids;         // Jobs submitted so far.
  std::vector<double> job_seconds;      // Submit to end, succeeded jobs.
  std::vector<double> get_ms;           // GetJob latencies.
  std::map<std::string, int> outcomes;  // Final states and failed calls by status code.
  void Count(const std::string& what) {
    std::lock_guard lock(mutex);
    ++outcomes[what];
  }
};

struct LoadOptions {
  std::string server = "127.0.0.1:50051";
  std::string cloud;
  int64_t points = 0;  // > 0: `cloud` is a mesh, sampled with this many points.
  std::string method = "iamls";
  std::vector<std::string> params;
  int jobs = 30;
  int submitters = 3;
  int pollers = 4;
  int poll_interval_ms = 50;
  double timeout_s = 3600;
};

void Submitter(const LoadOptions& o, const v1::JobSpec& spec, const std::string& input, std::atomic<int>& next,
               Clock::time_point deadline, Tally& tally) {
  lsqsurf::client::Client client(o.server);
  while (next.fetch_add(1) < o.jobs && Clock::now() < deadline) {
    const auto start = Clock::now();
    auto job = client.Submit(spec, input);
    if (!job.ok()) {
      tally.Count(std::string("submit ") + absl::StatusCodeToString(job.status().code()));
      continue;
    }
    {
      std::lock_guard lock(tally.mutex);
      tally.ids.push_back(job->id());
    }
    auto done = client.Watch(job->id());
    if (!done.ok()) {
      tally.Count(std::string("watch ") + absl::StatusCodeToString(done.status().code()));
      continue;
    }
    tally.Count(lsqsurf::client::StateName(done->state()));
    if (done->state() == v1::JOB_STATE_SUCCEEDED) {
      std::lock_guard lock(tally.mutex);
      tally.job_seconds.push_back(Seconds(Clock::now() - start));
    }
  }
}

void Poller(const LoadOptions& o, const std::atomic<bool>& stop, Tally& tally, unsigned seed) {
  lsqsurf::client::Client client(o.server);
  std::mt19937 rng(seed);
  while (!stop) {
    std::string id;
    {
      std::lock_guard lock(tally.mutex);
      if (!tally.ids.empty()) id = tally.ids[rng() % tally.ids.size()];
    }
    if (!id.empty()) {
      const auto start = Clock::now();
      auto job = client.Get(id);
      const double ms = Seconds(Clock::now() - start) * 1000;
      if (job.ok()) {
        std::lock_guard lock(tally.mutex);
        tally.get_ms.push_back(ms);
      } else {
        tally.Count(std::string("get ") + absl::StatusCodeToString(job.status().code()));
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(o.poll_interval_ms));
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf-load: concurrent jobs and status calls against a server, with latencies"};
  LoadOptions o;
  app.add_option("--server", o.server, "HOST:PORT of the server or balancer")->capture_default_str();
  app.add_option("--cloud", o.cloud, "point cloud every job uploads (PLY, OBJ, XYZ, Draco)")->required();
  app.add_option("--points", o.points, "read --cloud as a mesh and upload this many points sampled on it")
      ->check(CLI::Range(int64_t{16}, int64_t{100'000'000}));
  app.add_option("--method", o.method, "method of every job")->capture_default_str();
  app.add_option("--param", o.params, "NAME=VALUE for the method (repeatable)");
  app.add_option("--jobs", o.jobs, "jobs to submit")->capture_default_str()->check(CLI::Range(1, 100000));
  app.add_option("--submitters", o.submitters, "clients submitting and following jobs")
      ->capture_default_str()
      ->check(CLI::Range(1, 256));
  app.add_option("--pollers", o.pollers, "clients calling GetJob")->capture_default_str()->check(CLI::Range(0, 256));
  app.add_option("--poll-interval-ms", o.poll_interval_ms, "pause between one poller's calls")
      ->capture_default_str()
      ->check(CLI::Range(0, 60000));
  app.add_option("--timeout-s", o.timeout_s, "stop submitting after this long")->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  absl::StatusOr<lsqsurf::core::PointCloud> cloud = absl::UnknownError("");
  if (o.points > 0) {
    auto mesh = lsqsurf::io::ReadMeshFile(o.cloud);
    if (mesh.ok()) {
      cloud = lsqsurf::core::SampleCloud(*mesh, static_cast<size_t>(o.points), /*seed=*/1);
    } else {
      cloud = mesh.status();
    }
  } else {
    cloud = lsqsurf::io::ReadPointCloudFile(o.cloud);
  }
  if (!cloud.ok()) {
    std::fprintf(stderr, "lsqsurf-load: %s\n", std::string(cloud.status().message()).c_str());
    return 2;
  }
  auto input = lsqsurf::io::EncodeDracoPointCloud(*cloud, {});
  v1::JobSpec spec;
  absl::Status s = input.status();
  if (s.ok()) s = lsqsurf::client::SetMethod(&spec, o.method);
  for (const auto& p : o.params) {
    if (s.ok()) s = lsqsurf::client::SetParamAssignment(&spec, p);
  }
  if (!s.ok()) {
    std::fprintf(stderr, "lsqsurf-load: %s\n", std::string(s.message()).c_str());
    return 2;
  }

  Tally tally;
  std::atomic<int> next{0};
  std::atomic<bool> stop{false};
  const auto start = Clock::now();
  const auto deadline = start + std::chrono::milliseconds(static_cast<int64_t>(o.timeout_s * 1000));
  std::vector<std::thread> pollers, submitters;
  for (int i = 0; i < o.pollers; ++i) pollers.emplace_back([&, i] { Poller(o, stop, tally, 17u + i); });
  for (int i = 0; i < o.submitters; ++i) {
    submitters.emplace_back([&] { Submitter(o, spec, *input, next, deadline, tally); });
  }
  for (auto& t : submitters) t.join();
  const double wall = Seconds(Clock::now() - start);
  stop = true;
  for (auto& t : pollers) t.join();

  std::printf("server %s, %s on %zu points, %d jobs by %d submitters, %d pollers every %d ms\n", o.server.c_str(),
              o.method.c_str(), cloud->size(), o.jobs, o.submitters, o.pollers, o.poll_interval_ms);
  std::printf("wall %.1f s, %zu jobs succeeded: %.2f jobs/min\n", wall, tally.job_seconds.size(),
              60.0 * static_cast<double>(tally.job_seconds.size()) / wall);
  std::printf("job submit-to-end s: p50 %.2f  p90 %.2f  max %.2f\n", Percentile(tally.job_seconds, 50),
              Percentile(tally.job_seconds, 90), Percentile(tally.job_seconds, 100));
  std::printf("GetJob ms (%zu calls): p50 %.2f  p90 %.2f  p99 %.2f  max %.2f\n", tally.get_ms.size(),
              Percentile(tally.get_ms, 50), Percentile(tally.get_ms, 90), Percentile(tally.get_ms, 99),
              Percentile(tally.get_ms, 100));
  for (const auto& [what, n] : tally.outcomes) std::printf("  %-28s %d\n", what.c_str(), n);
  return tally.job_seconds.size() == static_cast<size_t>(o.jobs) ? 0 : 1;
}
