// Open streams cost no thread and are bounded: idle reflection streams (which need no token) and
// stalled uploads, held open by a client, neither grow the server's threads nor stop it from
// answering; past their bound new ones are refused, and idle ones are cancelled.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <thread>

#include "client/client.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "server/server.h"
#include "tests/latch_kind.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/io/draco_codec.h"

namespace lsqsurf::server {
namespace {

namespace reflection = grpc::reflection::v1alpha;

// This process's threads (the server's and the clients' alike), from /proc.
int ThreadCount() {
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("Threads:", 0) == 0) return std::stoi(line.substr(8));
  }
  return -1;
}

class StreamsTest : public ::testing::Test {
 protected:
  // `latch`, when given, stands in for apss's engine and checks.
  void Start(StreamLimits limits, testing::LatchKind* latch = nullptr) {
    dir_ = testing::FreshTestDir("lsqsurf-streams");
    jobs::JobServiceOptions options;
    options.data_dir = dir_.string();
    if (latch != nullptr) options.kind_overrides["apss"] = latch;
    auto jobs = jobs::JobService::Open(options);
    ASSERT_TRUE(jobs.ok()) << jobs.status();
    jobs_ = *std::move(jobs);
    ServerOptions server_options;
    server_options.streams = limits;
    // The tests open their streams on one connection; the per-connection bound is not under test.
    server_options.max_streams_per_connection = 1000;
    auto server = Server::Start(*jobs_, server_options);
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = *std::move(server);
  }
  void TearDown() override {
    latch_.ReleaseChecks();
    latch_.Release();
    server_.reset();  // Before the job service it serves.
    jobs_.reset();
    std::filesystem::remove_all(dir_);
  }
  std::shared_ptr<grpc::Channel> Channel() const {
    // Distinct channels: each stream limit per connection stays out of the way.
    grpc::ChannelArguments args;
    args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
    return grpc::CreateCustomChannel(address(), grpc::InsecureChannelCredentials(), args);
  }
  std::string address() const { return server_->address(); }

  std::filesystem::path dir_;
  testing::LatchKind latch_;  // Outlives the job service that may run it.
  std::unique_ptr<jobs::JobService> jobs_;
  std::unique_ptr<Server> server_;
};

TEST_F(StreamsTest, IdleStreamsHoldNoThreadAndAreBounded) {
  StreamLimits limits;
  limits.max_reflection = 150;
  limits.max_uploads = 60;
  limits.idle = std::chrono::hours(1);  // Not under test here.
  limits.per_user_share = 1.0;          // Nor the share of one client: every stream comes from here.
  Start(limits);
  auto channel = Channel();
  const int before = ThreadCount();

  // Reflection streams that ask nothing, and uploads that stop after their spec.
  auto reflection_stub = reflection::ServerReflection::NewStub(channel);
  auto stub = v1::Reconstruction::NewStub(channel);
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<
      grpc::ClientReaderWriter<reflection::ServerReflectionRequest, reflection::ServerReflectionResponse>>>
      idle;
  std::vector<std::unique_ptr<grpc::ClientWriter<v1::SubmitJobRequest>>> stalled;
  std::vector<v1::Job> responses(limits.max_uploads + 1);
  for (int i = 0; i < limits.max_reflection; ++i) {
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    idle.push_back(reflection_stub->ServerReflectionInfo(contexts.back().get()));
  }
  v1::SubmitJobRequest spec;
  spec.mutable_spec()->mutable_iamls();
  for (int i = 0; i < limits.max_uploads; ++i) {
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    stalled.push_back(stub->SubmitJob(contexts.back().get(), &responses[static_cast<size_t>(i)]));
    ASSERT_TRUE(stalled.back()->Write(spec));
  }
  // Every one is open on the server (counted there) before anything is measured.
  client::Client api(address());
  for (int round = 0;
       round < 1000 && (server_->service().streams().Open(StreamKind::kReflection) < limits.max_reflection ||
                        server_->service().streams().Open(StreamKind::kUpload) < limits.max_uploads);
       ++round) {
    ASSERT_TRUE(api.List(0).ok());  // A round trip: what the server had received is in by its answer.
  }
  EXPECT_EQ(server_->service().streams().Open(StreamKind::kReflection), limits.max_reflection);
  EXPECT_EQ(server_->service().streams().Open(StreamKind::kUpload), limits.max_uploads);

  // The API answers, and the threads did not grow with the streams (a synchronous server held
  // one for each of the 210).
  EXPECT_TRUE(api.List(0).ok());
  EXPECT_EQ(api.Get(std::string(32, '0')).status().code(), absl::StatusCode::kNotFound);
  const int during = ThreadCount();
  EXPECT_LT(during - before, 40) << before << " threads before, " << during << " with the streams open";

  // One more of each is refused, saying which bound.
  grpc::ClientContext over_context;
  auto over = reflection_stub->ServerReflectionInfo(&over_context);
  reflection::ServerReflectionResponse response;
  EXPECT_FALSE(over->Read(&response));
  const grpc::Status refused = over->Finish();
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(refused.error_message().find("--max-reflection-streams"), std::string::npos) << refused.error_message();
  grpc::ClientContext upload_context;
  auto upload = stub->SubmitJob(&upload_context, &responses.back());
  upload->Write(spec);
  upload->WritesDone();
  const grpc::Status upload_refused = upload->Finish();
  EXPECT_EQ(upload_refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(upload_refused.error_message().find("--max-uploads"), std::string::npos) << upload_refused.error_message();

  for (auto& c : contexts) c->TryCancel();
  for (auto& s : idle) s->Finish();
  for (auto& s : stalled) s->Finish();
}

TEST_F(StreamsTest, AnIdleStreamIsCancelledAndTheReflectionServiceAnswers) {
  StreamLimits limits;
  limits.idle = std::chrono::milliseconds(300);
  Start(limits);
  auto channel = Channel();
  auto reflection_stub = reflection::ServerReflection::NewStub(channel);
  // A stream that asks: the services, and the file that defines the API.
  grpc::ClientContext asking_context;
  auto asking = reflection_stub->ServerReflectionInfo(&asking_context);
  reflection::ServerReflectionRequest request;
  request.set_list_services("");
  ASSERT_TRUE(asking->Write(request));
  reflection::ServerReflectionResponse response;
  ASSERT_TRUE(asking->Read(&response));
  // The services lsqsurfd serves: the API, health and reflection.
  ASSERT_EQ(response.list_services_response().service_size(), 3);
  EXPECT_EQ(response.list_services_response().service(0).name(), ReconstructionService::kServiceName);
  EXPECT_EQ(response.list_services_response().service(1).name(), "grpc.health.v1.Health");
  request.set_file_containing_symbol(ReconstructionService::kServiceName);
  ASSERT_TRUE(asking->Write(request));
  ASSERT_TRUE(asking->Read(&response));
  ASSERT_GE(response.file_descriptor_response().file_descriptor_proto_size(), 1);
  google::protobuf::FileDescriptorProto file;
  // Dependencies come first; the API's own file last.
  ASSERT_TRUE(file.ParseFromString(response.file_descriptor_response().file_descriptor_proto(
      response.file_descriptor_response().file_descriptor_proto_size() - 1)));
  EXPECT_EQ(file.package(), "lsqsurf.v1");
  request.set_file_containing_symbol("no.such.Symbol");
  ASSERT_TRUE(asking->Write(request));
  ASSERT_TRUE(asking->Read(&response));
  EXPECT_EQ(response.error_response().error_code(), static_cast<int>(grpc::StatusCode::NOT_FOUND));
  asking->WritesDone();
  EXPECT_TRUE(asking->Finish().ok());

  // A stream that asks nothing is cancelled once idle: the client sees it end.
  grpc::ClientContext idle_context;
  auto idle = reflection_stub->ServerReflectionInfo(&idle_context);
  EXPECT_FALSE(idle->Read(&response));
  EXPECT_EQ(idle->Finish().error_code(), grpc::StatusCode::CANCELLED);
  // So is an upload that stops sending.
  auto stub = v1::Reconstruction::NewStub(channel);
  grpc::ClientContext upload_context;
  v1::Job job;
  auto upload = stub->SubmitJob(&upload_context, &job);
  v1::SubmitJobRequest spec;
  spec.mutable_spec()->mutable_iamls();
  ASSERT_TRUE(upload->Write(spec));
  EXPECT_EQ(upload->Finish().error_code(), grpc::StatusCode::CANCELLED);
}

TEST_F(StreamsTest, AFinishedUploadWaitingOnTheServerIsStoredNotCancelledAsIdle) {
  StreamLimits limits;
  limits.idle = std::chrono::milliseconds(300);
  testing::LatchKind& latch = latch_;
  latch.HoldChecks();
  Start(limits, &latch);
  client::Client client(address());
  v1::JobSpec spec;
  ASSERT_TRUE(client::SetMethod(&spec, "apss").ok());
  auto cloud = io::EncodeDracoPointCloud(testing::SphereCloud(500), {});
  ASSERT_TRUE(cloud.ok());
  // The upload is whole; its check holds the submission on the server for several idle limits
  // (the sweeper looks every second), while its client sends nothing more, as it should.
  std::thread release([&] {
    latch.WaitChecking(1);
    std::this_thread::sleep_for(std::chrono::milliseconds(2500));
    latch.ReleaseChecks();
  });
  auto job = client.Submit(spec, *cloud);
  release.join();
  ASSERT_TRUE(job.ok()) << job.status();  // Not CANCELLED (with the job stored all the same).
  auto listed = client.List(10);
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->jobs_size(), 1);
  EXPECT_EQ(listed->jobs(0).id(), job->id());
  latch.Release();
  EXPECT_EQ(client.Watch(job->id())->state(), v1::JOB_STATE_SUCCEEDED);
}

// A client without a token holds half of a kind's streams from its address: the rest stay for
// the others (one tokenless client held all 64 reflection slots).
TEST_F(StreamsTest, AClientWithoutATokenHoldsItsAddresssShare) {
  StreamLimits limits;
  limits.max_reflection = 8;
  limits.idle = std::chrono::hours(1);
  Start(limits);
  auto stub = reflection::ServerReflection::NewStub(Channel());
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<
      grpc::ClientReaderWriter<reflection::ServerReflectionRequest, reflection::ServerReflectionResponse>>>
      held;
  reflection::ServerReflectionRequest request;
  request.set_list_services("");
  reflection::ServerReflectionResponse response;
  for (int i = 0; i < 4; ++i) {  // Each answered once: it is open on the server.
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    held.push_back(stub->ServerReflectionInfo(contexts.back().get()));
    ASSERT_TRUE(held.back()->Write(request));
    ASSERT_TRUE(held.back()->Read(&response));
  }
  grpc::ClientContext fifth_context;
  auto fifth = stub->ServerReflectionInfo(&fifth_context);
  EXPECT_FALSE(fifth->Read(&response));
  const grpc::Status refused = fifth->Finish();
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(refused.error_message().find("your share"), std::string::npos) << refused.error_message();
  EXPECT_EQ(server_->service().streams().Open(StreamKind::kReflection), 4);
  for (auto& stream : held) stream->WritesDone();
  for (auto& stream : held) EXPECT_TRUE(stream->Finish().ok());

  EXPECT_EQ(PeerHolder("ipv4:127.0.0.1:54321"), "peer ipv4:127.0.0.1");
  EXPECT_EQ(PeerHolder("ipv6:[::1]:443"), "peer ipv6:[::1]");
  EXPECT_EQ(PeerHolder("unix:"), "peer unix:");
}

// Uploads in progress count before their jobs exist: against the disk's reserve for running
// jobs, and with the user's other uploads against the user's quota.
TEST(SpoolLedger, ChunksAreHeldToTheDisksReserveAndTheUsersQuota) {
  SpoolLedger ledger;
  SpoolLedger::Room room;
  room.disk_free = 100 << 20;
  room.min_free = 90 << 20;
  EXPECT_TRUE(ledger.Reserve("", 9 << 20, room).ok());
  room.disk_free = 91 << 20;  // As the disk shows once those are written.
  const absl::Status full = ledger.Reserve("", 2 << 20, room);
  EXPECT_EQ(full.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(full.message().find("disk is nearly full"), std::string_view::npos) << full;
  room.disk_free = -1;  // Unknown: only the quota holds.
  room.quota = 10 << 20;
  room.stored = 4 << 20;
  EXPECT_TRUE(ledger.Reserve("alice", 3 << 20, room).ok());  // Another upload of hers...
  EXPECT_TRUE(ledger.Reserve("alice", 3 << 20, room).ok());  // ...and this one: 4 + 6 MiB.
  const absl::Status over = ledger.Reserve("alice", 1, room);
  EXPECT_EQ(over.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(over.message().find("uploads in progress hold 6291456"), std::string_view::npos) << over;
  EXPECT_TRUE(ledger.Reserve("bob", 6 << 20, room).ok());  // Bob's quota is his own.
  ledger.Release("alice", 3 << 20);
  EXPECT_EQ(ledger.InFlight("alice"), 3 << 20);
  EXPECT_TRUE(ledger.Reserve("alice", 1, room).ok());
}

// A server whose disk has less free than its reserve stops an upload at its first chunk, and
// keeps no spool file of it.
TEST_F(StreamsTest, AnUploadStopsWhereTheDisksReserveBegins) {
  Start(StreamLimits{});
  std::error_code error;
  const auto space = std::filesystem::space(dir_, error);
  ASSERT_FALSE(error);
  // The reserve is a service option: a second service over the same folder, with one past the free space.
  server_.reset();
  jobs_.reset();
  jobs::JobServiceOptions options;
  options.data_dir = dir_.string();
  options.min_free_bytes = static_cast<int64_t>(space.available) + (int64_t{1} << 30);
  auto jobs = jobs::JobService::Open(options);
  ASSERT_TRUE(jobs.ok()) << jobs.status();
  jobs_ = *std::move(jobs);
  auto server = Server::Start(*jobs_, {});
  ASSERT_TRUE(server.ok()) << server.status();
  server_ = *std::move(server);
  client::Client client(address());
  v1::JobSpec spec;
  spec.mutable_iamls();
  auto cloud = io::EncodeDracoPointCloud(testing::SphereCloud(20000), {});
  ASSERT_TRUE(cloud.ok());
  const auto refused = client.Submit(spec, *cloud);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.status().message().find("the upload stops here"), std::string_view::npos) << refused.status();
  size_t spooled = 0;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(dir_)) {
    spooled += entry.path().parent_path().filename() == "uploads" && entry.is_regular_file();
  }
  EXPECT_EQ(spooled, 0u);
}

// Large uploads held in their checks on the server do not hold up a small one: it has a
// submission thread of its own (two large volume uploads once held a 19 KB submission 60 s).
TEST_F(StreamsTest, ASmallSubmissionPassesLargeOnesHeldInTheirChecks) {
  latch_.HoldChecks();
  Start(StreamLimits{}, &latch_);  // apss: held in its check.
  std::vector<std::thread> large;
  std::vector<absl::StatusOr<v1::Job>> large_jobs(3);
  v1::JobSpec apss;
  ASSERT_TRUE(client::SetMethod(&apss, "apss").ok());
  const std::string big(3 << 19, 'x');  // 1.5 MiB: the check (the latch's) does not read it.
  for (size_t k = 0; k < large_jobs.size(); ++k) {
    large.emplace_back([&, k] { large_jobs[k] = client::Client(address()).Submit(apss, big); });
  }
  latch_.WaitChecking(2);  // Both threads that take large uploads hold one each.
  std::atomic<bool> small_done{false};
  std::thread watchdog([&] {  // Lets them go after 20 s at the latest, so a failure cannot hang.
    for (int i = 0; i < 400 && !small_done; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(50));
    latch_.ReleaseChecks();
  });
  v1::JobSpec iamls;
  iamls.mutable_iamls();
  auto cloud = io::EncodeDracoPointCloud(testing::SphereCloud(500), {});
  ASSERT_TRUE(cloud.ok());
  auto small = client::Client(address()).Submit(iamls, *cloud);
  EXPECT_TRUE(latch_.ChecksHeld());  // Accepted while the large ones still wait.
  small_done = true;
  watchdog.join();
  for (std::thread& t : large) t.join();
  ASSERT_TRUE(small.ok()) << small.status();
  for (const auto& job : large_jobs) EXPECT_TRUE(job.ok()) << job.status();
  latch_.Release();
}

}  // namespace
}  // namespace lsqsurf::server
