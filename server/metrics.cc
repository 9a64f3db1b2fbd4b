#include "server/metrics.h"

#include <prometheus/collectable.h>
#include <prometheus/counter.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>
#include <prometheus/text_serializer.h>

#include <atomic>
#include <cctype>
#include <map>
#include <mutex>

#include "worker/core/strings.h"
#include "worker/jobs/job_service.h"

namespace lsqsurf::server {
namespace {

// Seconds, from a status call to a night-long job.
const prometheus::Histogram::BucketBoundaries& CallBuckets() {
  static const auto* b = new prometheus::Histogram::BucketBoundaries{0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1,
                                                                     0.25,  0.5,    1,     2.5,  5,     10,   30};
  return *b;
}
const prometheus::Histogram::BucketBoundaries& JobBuckets() {
  static const auto* b =
      new prometheus::Histogram::BucketBoundaries{0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600, 1800, 3600};
  return *b;
}

// Job counts by state and method, and the queue depth, computed when scraped.
class JobGauges final : public prometheus::Collectable {
 public:
  void Watch(const jobs::JobService* service) { service_ = service; }
  std::vector<prometheus::MetricFamily> Collect() const override {
    prometheus::MetricFamily jobs{
        "lsqsurf_jobs", "Jobs on record by state and method", prometheus::MetricType::Gauge, {}};
    prometheus::MetricFamily queue{"lsqsurf_queue_depth", "Queued jobs", prometheus::MetricType::Gauge, {}};
    const jobs::JobService* service = service_.load();
    std::map<std::pair<std::string, std::string>, int> counts;
    int queued = 0;
    if (service != nullptr) {
      for (const jobs::JobRecord& r : service->List()) {
        ++counts[{jobs::JobStateName(r.state), r.spec.method}];
        queued += r.state == jobs::JobState::kQueued;
      }
    }
    for (const auto& [key, n] : counts) {
      prometheus::ClientMetric m;
      m.label = {{"state", key.first}, {"method", key.second}};
      m.gauge.value = n;
      jobs.metric.push_back(std::move(m));
    }
    prometheus::ClientMetric depth;
    depth.gauge.value = queued;
    queue.metric.push_back(std::move(depth));
    return {std::move(jobs), std::move(queue)};
  }

 private:
  std::atomic<const jobs::JobService*> service_{nullptr};
};

}  // namespace

struct Metrics::State {
  std::shared_ptr<prometheus::Registry> registry = std::make_shared<prometheus::Registry>();
  std::shared_ptr<JobGauges> gauges = std::make_shared<JobGauges>();
  std::unique_ptr<HttpFront> front;
  prometheus::Family<prometheus::Histogram>* job_seconds = nullptr;
  prometheus::Family<prometheus::Histogram>* stage_seconds = nullptr;
  prometheus::Family<prometheus::Histogram>* call_seconds = nullptr;
  prometheus::Family<prometheus::Counter>* call_errors = nullptr;
  prometheus::Counter* received = nullptr;
  prometheus::Counter* sent = nullptr;
  prometheus::Counter* frames = nullptr;
};

Metrics::Metrics() : state_(std::make_unique<State>()) {}
Metrics::~Metrics() = default;

absl::StatusOr<std::shared_ptr<Metrics>> Metrics::Start(const HttpFrontOptions& options) {
  std::shared_ptr<Metrics> metrics(new Metrics());
  State& s = *metrics->state_;
  s.job_seconds = &prometheus::BuildHistogram()
                       .Name("lsqsurf_job_duration_seconds")
                       .Help("Runs this server finished, from start to end, by method and final state")
                       .Register(*s.registry);
  s.stage_seconds = &prometheus::BuildHistogram()
                         .Name("lsqsurf_stage_duration_seconds")
                         .Help("Stages of the runs this server made, by method and stage")
                         .Register(*s.registry);
  s.call_seconds = &prometheus::BuildHistogram()
                        .Name("lsqsurf_rpc_duration_seconds")
                        .Help("Calls of the lsqsurf.v1 API, by rpc, whatever their outcome")
                        .Register(*s.registry);
  s.call_errors = &prometheus::BuildCounter()
                       .Name("lsqsurf_rpc_errors_total")
                       .Help("Calls answered with an error, by rpc and gRPC status code")
                       .Register(*s.registry);
  s.received = &prometheus::BuildCounter()
                    .Name("lsqsurf_received_bytes_total")
                    .Help("Upload bytes received")
                    .Register(*s.registry)
                    .Add({});
  s.sent = &prometheus::BuildCounter()
                .Name("lsqsurf_sent_bytes_total")
                .Help("Result and picture bytes sent")
                .Register(*s.registry)
                .Add({});
  s.frames = &prometheus::BuildCounter()
                  .Name("lsqsurf_render_frames_total")
                  .Help("Pictures drawn through Render")
                  .Register(*s.registry)
                  .Add({});
  // The scrape is served by the same bounded front as the job page: a slow or silent client holds
  // no thread and none of the server's memory past its head.
  auto front = HttpFront::Start(options, [&s](const HttpRequest& request) {
    HttpAnswer answer;
    if (request.path != "/metrics") {
      answer.status = 404;
      answer.body = "lsqsurfd serves its metrics at /metrics\n";
      return answer;
    }
    std::vector<prometheus::MetricFamily> families = s.registry->Collect();
    for (prometheus::MetricFamily& family : s.gauges->Collect()) families.push_back(std::move(family));
    answer.headers = {{"Content-Type", "text/plain; version=0.0.4; charset=utf-8"}};
    answer.body = prometheus::TextSerializer().Serialize(families);
    return answer;
  });
  if (!front.ok()) {
    return absl::UnavailableError(
        core::StrCat("cannot serve metrics on ", options.listen, ": ", front.status().message()));
  }
  s.front = *std::move(front);
  return metrics;
}

void Metrics::Watch(const jobs::JobService* service) { state_->gauges->Watch(service); }

void Metrics::Stop() {
  state_->front.reset();  // Joins its threads: no scrape is left in flight.
  state_->gauges->Watch(nullptr);
}

std::string StageLabel(std::string_view stage) {
  std::string out;
  for (size_t i = 0; i < stage.size();) {
    // A number starts a word: a digit, or a sign or point before one.
    const bool word_start = i == 0 || stage[i - 1] == ' ';
    size_t j = i;
    while (j < stage.size() && (stage[j] == '-' || stage[j] == '+' || stage[j] == '.')) ++j;
    if (word_start && j < stage.size() && std::isdigit(static_cast<unsigned char>(stage[j]))) {
      while (j < stage.size() && stage[j] != ' ' && stage[j] != ':' && stage[j] != ',') ++j;
      out += '#';
      i = j;
      continue;
    }
    out += stage[i++];
  }
  return out;
}

void Metrics::StageEnded(const std::string& method, const std::string& stage, double seconds) {
  state_->stage_seconds->Add({{"method", method}, {"stage", StageLabel(stage)}}, JobBuckets()).Observe(seconds);
}

void Metrics::JobEnded(const std::string& method, jobs::JobState state, double seconds) {
  state_->job_seconds->Add({{"method", method}, {"state", jobs::JobStateName(state)}}, JobBuckets()).Observe(seconds);
}

void Metrics::CallEnded(std::string_view rpc, int code, double seconds) {
  const std::string name(rpc);
  state_->call_seconds->Add({{"rpc", name}}, CallBuckets()).Observe(seconds);
  if (code != 0) {
    state_->call_errors->Add({{"rpc", name}, {"code", absl::StatusCodeToString(static_cast<absl::StatusCode>(code))}})
        .Increment();
  }
}

void Metrics::Received(int64_t bytes) { state_->received->Increment(static_cast<double>(bytes)); }
void Metrics::Sent(int64_t bytes) { state_->sent->Increment(static_cast<double>(bytes)); }
void Metrics::FrameRendered() { state_->frames->Increment(); }

}  // namespace lsqsurf::server
