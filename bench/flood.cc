// lsqsurf-flood — holds many streams open against a running lsqsurfd, the way a client that means
// harm would, and measures what that costs the server and whether it still answers.
//
//   lsqsurf-flood --server 127.0.0.1:50051 --server-pid PID --reflection 5000 --uploads 1000
//
// Opens `reflection` server-reflection streams that ask nothing (they need no token) and
// `uploads` SubmitJob streams that send their spec and one chunk, then stall; spreads them over
// connections of at most --per-connection streams. Then times --probes GetJob calls on a fresh
// connection and prints their percentiles, how many streams the server admitted (the rest were
// refused, which is also a right answer), and the server's threads and resident memory (from
// /proc/PID/status) before and with the streams open. Nothing is measured until every stream has
// been answered or is known open.
//
// --watches N follows one long-running job (a front-tracking run, cancelled at the end) with N
// WatchJob streams, so GetJob is timed while a worker computes. --upload-mib M first sends one
// upload of M MiB (bytes that are no cloud, refused once spooled) and reports how far it moved
// the server's peak resident memory (VmHWM).
//
// --missing-volume N submits, as one user, a volume of N^3 vertices (hexahedra) whose field is
// missing (NaN, in an unquantized Draco attribute as a client of its own may send) at half of
// them, and meanwhile times small cloud submissions as another user would make them; it prints
// their slowest time against the same submissions on the idle server, then exits.
#include <draco/compression/encode.h>
#include <draco/metadata/geometry_metadata.h>
#include <draco/point_cloud/point_cloud.h>
#include <grpcpp/grpcpp.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "client/client.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "worker/core/volume_mesh.h"
#include "worker/io/draco_codec.h"
#include "worker/io/volume_codec.h"

namespace {

namespace reflection = grpc::reflection::v1alpha;

struct ProcessStatus {
  int threads = -1;
  long rss_kib = -1;
  long peak_kib = -1;  // VmHWM: the most it was ever resident.
};

ProcessStatus ReadStatus(int pid) {
  ProcessStatus s;
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("Threads:", 0) == 0) s.threads = std::stoi(line.substr(8));
    if (line.rfind("VmRSS:", 0) == 0) s.rss_kib = std::stol(line.substr(6));
    if (line.rfind("VmHWM:", 0) == 0) s.peak_kib = std::stol(line.substr(6));
  }
  return s;
}

struct Options {
  std::string server = "127.0.0.1:50051";
  int server_pid = 0;
  int reflection = 5000;
  int uploads = 1000;
  int per_connection = 90;
  int chunk_kib = 64;
  int probes = 2000;
  int watches = 0;         // WatchJob streams on one running job.
  int upload_mib = 0;      // One upload of this size, sent whole before the streams open.
  int missing_volume = 0;  // Side of the half-missing volume grid; 0: none.
};

// Sends `mib` MiB in 1 MiB chunks as one upload (bytes that are no cloud: the server spools them
// and then refuses them, so what is measured is the transport) and returns the server's answer.
grpc::Status BigUpload(const std::string& server, int mib, int pid, ProcessStatus* streamed) {
  auto stub = lsqsurf::v1::Reconstruction::NewStub(grpc::CreateChannel(server, grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  lsqsurf::v1::Job response;
  auto writer = stub->SubmitJob(&context, &response);
  lsqsurf::v1::SubmitJobRequest request;
  request.mutable_spec()->mutable_iamls();
  writer->Write(request);
  request.Clear();
  request.set_input_chunk(std::string(size_t{1} << 20, 'x'));
  for (int i = 0; i < mib && writer->Write(request); ++i) {
  }
  // Every chunk is in once the server answers another call: what streaming alone cost.
  (void)lsqsurf::client::Client(server).List(1);
  if (pid > 0) *streamed = ReadStatus(pid);
  writer->WritesDone();
  return writer->Finish();
}

// A job that runs for minutes (a long front-tracking run), for watchers to follow.
absl::StatusOr<std::string> LongJob(lsqsurf::client::Client& api) {
  lsqsurf::v1::JobSpec spec;
  spec.mutable_track()->set_interface(lsqsurf::v1::TrackParams::INTERFACE_SPHERE);
  spec.mutable_track()->set_steps(100000);
  spec.mutable_track()->set_stride(100000);
  auto job = api.Submit(spec, "");
  if (!job.ok()) return job.status();
  return job->id();
}

// Sends one upload of --upload-mib and prints how far it moved the server's peak memory.
void ReportBigUpload(const Options& o) {
  const ProcessStatus start = o.server_pid > 0 ? ReadStatus(o.server_pid) : ProcessStatus{};
  const auto upload_start = std::chrono::steady_clock::now();
  ProcessStatus streamed;
  const grpc::Status answer = BigUpload(o.server, o.upload_mib, o.server_pid, &streamed);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - upload_start).count();
  const ProcessStatus end = o.server_pid > 0 ? ReadStatus(o.server_pid) : ProcessStatus{};
  const auto mib = [](long kib) { return static_cast<double>(kib) / 1024.0; };
  std::printf(
      "upload: %d MiB in %.1f s, answered %d (%s); server peak %.1f MiB before, %.1f MiB once streamed "
      "(+%.1f MiB), %.1f MiB after its end (+%.1f MiB)\n",
      o.upload_mib, seconds, static_cast<int>(answer.error_code()), answer.error_message().substr(0, 80).c_str(),
      mib(start.peak_kib), mib(streamed.peak_kib), mib(streamed.peak_kib - start.peak_kib), mib(end.peak_kib),
      mib(end.peak_kib - start.peak_kib));
}

// The vertices of an n^3 grid with field "f" missing (NaN) where x < n/2, as a Draco point cloud
// with positions quantized and the field kept as raw floats (NaN travels).
std::string HalfMissingVertices(int n) {
  draco::PointCloud pc;
  const auto count = static_cast<uint32_t>(n) * static_cast<uint32_t>(n) * static_cast<uint32_t>(n);
  pc.set_num_points(count);
  draco::GeometryAttribute position, value;
  position.Init(draco::GeometryAttribute::POSITION, nullptr, 3, draco::DT_FLOAT32, false, 12, 0);
  value.Init(draco::GeometryAttribute::GENERIC, nullptr, 1, draco::DT_FLOAT32, false, 4, 0);
  draco::PointAttribute* p = pc.attribute(pc.AddAttribute(position, true, count));
  const int value_id = pc.AddAttribute(value, true, count);
  draco::PointAttribute* v = pc.attribute(value_id);
  uint32_t i = 0;
  for (int z = 0; z < n; ++z) {
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x, ++i) {
        const float xyz[3] = {static_cast<float>(x), static_cast<float>(y), static_cast<float>(z)};
        const float f = x < n / 2 ? std::nanf("") : static_cast<float>(x + y + z) / static_cast<float>(3 * n);
        p->SetAttributeValue(draco::AttributeValueIndex(i), xyz);
        v->SetAttributeValue(draco::AttributeValueIndex(i), &f);
      }
    }
  }
  auto name = std::make_unique<draco::AttributeMetadata>();
  name->AddEntryString("name", "f");
  pc.AddAttributeMetadata(value_id, std::move(name));
  draco::Encoder encoder;
  encoder.SetAttributeQuantization(draco::GeometryAttribute::POSITION, 20);
  encoder.SetSpeedOptions(10, 10);  // Sequential: the cells refer to the vertex order.
  draco::EncoderBuffer buffer;
  if (!encoder.EncodePointCloudToBuffer(pc, &buffer).ok()) return {};
  return std::string(buffer.data(), buffer.size());
}

// Submits the half-missing volume while timing small submissions; prints the times.
int ReportMissingVolume(const Options& o) {
  lsqsurf::core::VolumeMesh cells;
  lsqsurf::core::AddStructuredHexahedra(cells, o.missing_volume, o.missing_volume, o.missing_volume);
  const std::string vertices = HalfMissingVertices(o.missing_volume);
  lsqsurf::core::PointCloud sphere;
  for (int i = 0; i < 500; ++i) {
    const float z = 1.0f - 2.0f * (static_cast<float>(i) + 0.5f) / 500.0f, r = std::sqrt(1.0f - z * z);
    sphere.positions.push_back(
        {r * std::cos(2.4f * static_cast<float>(i)), r * std::sin(2.4f * static_cast<float>(i)), z});
  }
  const std::string small = lsqsurf::io::EncodeDracoPointCloud(sphere, {}).value();
  lsqsurf::v1::JobSpec small_spec, volume_spec;
  small_spec.mutable_iamls();
  volume_spec.mutable_volume()->set_field("f");
  lsqsurf::client::Client small_api(o.server), volume_api(o.server);
  const auto time_small = [&] {
    const auto start = std::chrono::steady_clock::now();
    auto job = small_api.Submit(small_spec, small);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    if (job.ok()) (void)small_api.Cancel(job->id());             // Untimed; the queue stays short.
    std::this_thread::sleep_for(std::chrono::milliseconds(20));  // A user's pace, not a flood.
    return job.ok() ? ms : -1.0;
  };
  std::vector<double> idle;
  for (int i = 0; i < 5; ++i) idle.push_back(time_small());
  std::sort(idle.begin(), idle.end());
  std::atomic<bool> done{false};
  absl::Status volume_answer;
  double volume_seconds = 0;
  std::thread volume([&] {
    const auto start = std::chrono::steady_clock::now();
    volume_answer = volume_api.Submit(volume_spec, vertices, {}, lsqsurf::io::EncodeCellStream(cells)).status();
    volume_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    done = true;
  });
  std::vector<double> meanwhile;
  while (!done) meanwhile.push_back(time_small());
  volume.join();
  const double slowest = meanwhile.empty() ? 0.0 : *std::max_element(meanwhile.begin(), meanwhile.end());
  const bool all_accepted = std::none_of(meanwhile.begin(), meanwhile.end(), [](double ms) { return ms < 0; });
  std::printf(
      "missing volume: %d vertices (half NaN), %.1f MB, submitted in %.2f s: %s\n"
      "small submissions meanwhile: %zu, %s; slowest %.0f ms, idle median %.0f ms: delayed by %.0f ms\n",
      o.missing_volume * o.missing_volume * o.missing_volume, static_cast<double>(vertices.size()) / 1e6,
      volume_seconds, volume_answer.ok() ? "accepted" : std::string(volume_answer.message()).c_str(), meanwhile.size(),
      all_accepted ? "all accepted" : "SOME REFUSED", slowest, idle[idle.size() / 2], slowest - idle[idle.size() / 2]);
  return volume_answer.ok() && all_accepted ? 0 : 1;
}

// Times --probes GetJob calls of a missing id, in milliseconds; `answered` counts the NOT_FOUND.
// On a connection of its own, after a few untimed calls: what the streams sent is in by then.
std::vector<double> TimeGetJob(const Options& o, int* answered) {
  lsqsurf::client::Client api(o.server);
  for (int i = 0; i < 20; ++i) (void)api.List(1);
  const std::string missing(32, '0');
  std::vector<double> ms;
  for (int i = 0; i < o.probes; ++i) {
    const auto start = std::chrono::steady_clock::now();
    const auto status = api.Get(missing).status();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
    *answered += status.code() == absl::StatusCode::kNotFound;
  }
  return ms;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf-flood: many idle streams against lsqsurfd, and GetJob latency meanwhile"};
  Options o;
  app.add_option("--server", o.server, "HOST:PORT")->capture_default_str();
  app.add_option("--server-pid", o.server_pid, "the server's process id, to read its threads and memory");
  app.add_option("--reflection", o.reflection, "idle reflection streams")->capture_default_str();
  app.add_option("--uploads", o.uploads, "stalled uploads")->capture_default_str();
  app.add_option("--per-connection", o.per_connection, "streams per connection")->capture_default_str();
  app.add_option("--chunk-kib", o.chunk_kib, "bytes each upload sends before it stalls, KiB")->capture_default_str();
  app.add_option("--probes", o.probes, "GetJob calls timed with the streams open")->capture_default_str();
  app.add_option("--watches", o.watches, "WatchJob streams on one long-running job")->capture_default_str();
  app.add_option("--upload-mib", o.upload_mib, "first, one upload of this many MiB (its peak memory is reported)")
      ->capture_default_str();
  app.add_option("--missing-volume", o.missing_volume,
                 "only submit an N^3 volume with half its values missing, timing small submissions meanwhile");
  CLI11_PARSE(app, argc, argv);

  if (o.missing_volume > 0) return ReportMissingVolume(o);
  if (o.upload_mib > 0) ReportBigUpload(o);
  lsqsurf::client::Client watched_api(o.server);
  std::string watched;
  if (o.watches > 0) {
    auto id = LongJob(watched_api);
    if (!id.ok()) {
      std::fprintf(stderr, "lsqsurf-flood: could not submit the job to watch: %s\n",
                   std::string(id.status().message()).c_str());
      return 1;
    }
    watched = *id;
  }
  const ProcessStatus before = o.server_pid > 0 ? ReadStatus(o.server_pid) : ProcessStatus{};
  std::vector<std::shared_ptr<grpc::Channel>> channels;
  int on_channel = o.per_connection;
  auto channel = [&] {
    if (on_channel >= o.per_connection) {
      grpc::ChannelArguments args;
      args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);  // A connection of its own.
      channels.push_back(grpc::CreateCustomChannel(o.server, grpc::InsecureChannelCredentials(), args));
      on_channel = 0;
    }
    ++on_channel;
    return channels.back();
  };
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<
      grpc::ClientReaderWriter<reflection::ServerReflectionRequest, reflection::ServerReflectionResponse>>>
      idle;
  std::vector<std::unique_ptr<grpc::ClientWriter<lsqsurf::v1::SubmitJobRequest>>> stalled;
  std::vector<lsqsurf::v1::Job> responses(static_cast<size_t>(o.uploads));
  const auto open_start = std::chrono::steady_clock::now();
  for (int i = 0; i < o.reflection; ++i) {
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    idle.push_back(reflection::ServerReflection::NewStub(channel())->ServerReflectionInfo(contexts.back().get()));
  }
  lsqsurf::v1::SubmitJobRequest spec, chunk;
  spec.mutable_spec()->mutable_iamls();
  chunk.set_input_chunk(std::string(static_cast<size_t>(o.chunk_kib) << 10, 'x'));
  int uploads_writing = 0;
  for (int i = 0; i < o.uploads; ++i) {
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    stalled.push_back(lsqsurf::v1::Reconstruction::NewStub(channel())->SubmitJob(contexts.back().get(),
                                                                                 &responses[static_cast<size_t>(i)]));
    // A refused upload's writes fail; an admitted one takes both.
    uploads_writing += stalled.back()->Write(spec) && stalled.back()->Write(chunk);
  }
  std::vector<std::unique_ptr<grpc::ClientReader<lsqsurf::v1::JobEvent>>> watchers;
  lsqsurf::v1::WatchJobRequest watch_request;
  watch_request.set_job_id(watched);
  for (int i = 0; i < o.watches; ++i) {
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    watchers.push_back(lsqsurf::v1::Reconstruction::NewStub(channel())->WatchJob(contexts.back().get(), watch_request));
  }
  int watching = 0;
  for (auto& w : watchers) {
    lsqsurf::v1::JobEvent first;
    watching += w->Read(&first);  // Each admitted watcher gets the job's state at once.
  }
  const double open_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - open_start).count();

  int answered = 0;
  std::vector<double> ms = TimeGetJob(o, &answered);
  std::sort(ms.begin(), ms.end());
  const auto pct = [&](double p) {
    return ms.empty() ? 0.0 : ms[std::min(ms.size() - 1, static_cast<size_t>(p * static_cast<double>(ms.size())))];
  };
  const ProcessStatus during = o.server_pid > 0 ? ReadStatus(o.server_pid) : ProcessStatus{};

  std::printf(
      "streams: %d reflection, %d uploads and %d watches (%d answered) opened in %.1f s over %zu connections; %d "
      "uploads still writable after their chunk\n",
      o.reflection, o.uploads, o.watches, watching, open_seconds, channels.size(), uploads_writing);
  std::printf("GetJob: %d of %d answered NOT_FOUND; p50 %.2f ms, p99 %.2f ms, max %.2f ms\n", answered, o.probes,
              pct(0.5), pct(0.99), ms.empty() ? 0.0 : ms.back());
  if (o.server_pid > 0) {
    std::printf(
        "server: %d threads before, %d with the streams open; resident %.1f MiB before, %.1f MiB with them "
        "(+%.1f MiB)\n",
        before.threads, during.threads, static_cast<double>(before.rss_kib) / 1024.0,
        static_cast<double>(during.rss_kib) / 1024.0, static_cast<double>(during.rss_kib - before.rss_kib) / 1024.0);
  }
  // Which were admitted: each stream is closed; a refused one ended with RESOURCE_EXHAUSTED at
  // once, an admitted one ends now (a reflection stream with OK, an upload of junk refused as such).
  int refused_reflection = 0, refused_uploads = 0;
  for (auto& s : idle) {
    s->WritesDone();
    refused_reflection += s->Finish().error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED;
  }
  for (auto& s : stalled) {
    s->WritesDone();
    refused_uploads += s->Finish().error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED;
  }
  std::printf("refused at once: %d reflection streams, %d uploads (RESOURCE_EXHAUSTED)\n", refused_reflection,
              refused_uploads);
  if (!watched.empty()) {
    (void)watched_api.Cancel(watched);
    for (auto& c : contexts) c->TryCancel();
    for (auto& w : watchers) (void)w->Finish();
  }
  return answered == o.probes ? 0 : 1;
}
