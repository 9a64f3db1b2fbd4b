// server/metrics.h — a Prometheus endpoint for lsqsurfd (--metrics-listen HOST:PORT).
//
// Metrics (all prefixed lsqsurf_):
//   jobs{state,method}                   gauge: jobs on record, as this server sees the store
//   queue_depth                          gauge: queued jobs
//   job_duration_seconds{method,state}   histogram: runs this server finished, start to end
//   stage_duration_seconds{method,stage} histogram: stages of those runs
//   rpc_duration_seconds{rpc}            histogram: every call, successful or not
//   rpc_errors_total{rpc,code}           counter: calls answered with an error, by status code
//                                        (rejections: INVALID_ARGUMENT, RESOURCE_EXHAUSTED, ...)
//   received_bytes_total                 counter: upload bytes received
//   sent_bytes_total                     counter: result and picture bytes sent
//   render_frames_total                  counter: pictures drawn through Render
// With a shared store every server reports the same jobs and queue: read those from one server,
// and sum the others (durations, calls, bytes) over all of them.
#pragma once

#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "server/http_front.h"
#include "worker/jobs/job_events.h"

namespace lsqsurf::jobs {
class JobService;
}

namespace lsqsurf::server {

// What the gRPC layer reports of each call.
class CallObserver {
 public:
  virtual ~CallObserver() = default;
  virtual void CallEnded(std::string_view rpc, int code, double seconds) = 0;  // code: grpc::StatusCode.
  virtual void Received(int64_t bytes) = 0;
  virtual void Sent(int64_t bytes) = 0;
  virtual void FrameRendered() = 0;
};

// A job stage as a metric label: its numbers (iso-values, levels, which a user's parameters
// choose) become '#', so that the labels come from a fixed set ("volume: isosurface #: ...").
std::string StageLabel(std::string_view stage);

class Metrics final : public jobs::JobEvents, public CallObserver {
 public:
  // Serves /metrics on `options.listen` (HOST:PORT; port 0 picks one) under the HTTP front's
  // bounds and Host check. Errors: kUnavailable when the address cannot be bound.
  static absl::StatusOr<std::shared_ptr<Metrics>> Start(const HttpFrontOptions& options);
  ~Metrics() override;

  // The jobs whose counts the gauges report; set once the service is open.
  void Watch(const jobs::JobService* service);
  // Stops serving (before the job service goes away).
  void Stop();

  void StageEnded(const std::string& method, const std::string& stage, double seconds) override;
  void JobEnded(const std::string& method, jobs::JobState state, double seconds) override;
  void CallEnded(std::string_view rpc, int code, double seconds) override;
  void Received(int64_t bytes) override;
  void Sent(int64_t bytes) override;
  void FrameRendered() override;

 private:
  struct State;
  Metrics();
  std::unique_ptr<State> state_;
};

}  // namespace lsqsurf::server
