// Open streams cost no thread and are bounded: idle reflection streams (which need no token) and
// stalled uploads, held open by a client, neither grow the server's threads nor stop it from
// answering; past their bound new ones are refused, and idle ones are cancelled.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "client/client.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "server/server.h"
#include "tests/test_dir.h"

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
  void Start(StreamLimits limits) {
    dir_ = testing::FreshTestDir("lsqsurf-streams");
    jobs::JobServiceOptions options;
    options.data_dir = dir_.string();
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
  std::unique_ptr<jobs::JobService> jobs_;
  std::unique_ptr<Server> server_;
};

TEST_F(StreamsTest, IdleStreamsHoldNoThreadAndAreBounded) {
  StreamLimits limits;
  limits.max_reflection = 150;
  limits.max_uploads = 60;
  limits.idle = std::chrono::hours(1);  // Not under test here.
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

}  // namespace
}  // namespace lsqsurf::server
