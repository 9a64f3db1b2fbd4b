// The HTTP gateway (lsqsurfd --http-listen) in this process, on a gRPC server with tokens: what a
// browser's requests get, read back with protobuf's own JSON parser, against what the gRPC API
// gives the same token. A job held running by a latch stands for a running one.
#include "server/http_gateway.h"

#include <google/protobuf/util/json_util.h>
#include <gtest/gtest.h>

#include <filesystem>

#include "client/client.h"
#include "server/server.h"
#include "server/tokens.h"
#include "server/web_assets.h"
#include "tests/latch_kind.h"
#include "tests/server/http_get.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/io/draco_codec.h"

namespace lsqsurf::server {
namespace {

namespace fs = std::filesystem;

template <class Message>
Message FromJson(const std::string& json) {
  Message message;
  const auto status = google::protobuf::util::JsonStringToMessage(json, &message);
  EXPECT_TRUE(status.ok()) << status << ": " << json;
  return message;
}

std::string Bearer(const std::string& token) { return "Bearer " + token; }

class HttpGatewayTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-http");
    fs::create_directories(dir_);
    for (auto [name, token] : {std::pair{"alice", &alice_}, {"bob", &bob_}}) {
      TokenEntry entry;
      entry.name = name;
      entry.role = Role::kUser;
      auto made = AddToken((dir_ / "tokens").string(), entry);
      ASSERT_TRUE(made.ok()) << made.status();
      *token = *made;
    }
    auto tokens = TokenTable::Load((dir_ / "tokens").string());
    ASSERT_TRUE(tokens.ok()) << tokens.status();
    tokens_ = *std::move(tokens);
    jobs::JobServiceOptions options;
    options.data_dir = (dir_ / "data").string();
    options.kind_overrides["apss"] = &latch_;
    auto jobs = jobs::JobService::Open(options);
    ASSERT_TRUE(jobs.ok()) << jobs.status();
    jobs_ = *std::move(jobs);
    ServerOptions server_options;
    server_options.tokens = tokens_.get();
    auto server = Server::Start(*jobs_, server_options);
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = *std::move(server);
    auto gateway = HttpGateway::Start(server_->InProcessChannel(), {});
    ASSERT_TRUE(gateway.ok()) << gateway.status();
    gateway_ = *std::move(gateway);
  }
  void TearDown() override {
    latch_.Release();
    gateway_.reset();
    server_.reset();
    jobs_.reset();
    fs::remove_all(dir_);
  }
  testing::HttpReply Get(const std::string& path, const std::string& authorization = "") {
    return testing::HttpGet(gateway_->address(), path, authorization);
  }
  client::Client Connect(const std::string& token) {
    client::ConnectOptions options;
    options.token = token;
    return client::Client(server_->address(), options);
  }
  // A job of `method` submitted by alice over gRPC, on a sphere of `points` points.
  v1::Job Submit(const std::string& method, int points) {
    v1::JobSpec spec;
    EXPECT_TRUE(client::SetMethod(&spec, method).ok());
    auto cloud = io::EncodeDracoPointCloud(testing::SphereCloud(points), {});
    EXPECT_TRUE(cloud.ok());
    auto job = Connect(alice_).Submit(spec, *cloud);
    EXPECT_TRUE(job.ok()) << job.status();
    return *job;
  }

  fs::path dir_;
  std::string alice_, bob_;
  std::unique_ptr<TokenTable> tokens_;
  testing::LatchKind latch_;
  std::unique_ptr<jobs::JobService> jobs_;
  std::unique_ptr<Server> server_;
  std::unique_ptr<HttpGateway> gateway_;
};

TEST_F(HttpGatewayTest, AUserSeesTheirJobsAndNoOneElsesWithTheGrpcRefusals) {
  const v1::Job done = Submit("iamls", 3000);
  ASSERT_EQ(Connect(alice_).Watch(done.id())->state(), v1::JOB_STATE_SUCCEEDED);
  const v1::Job held = Submit("apss", 500);
  latch_.WaitStarted(1);

  auto anonymous = Get("/api/jobs");
  ASSERT_TRUE(anonymous.ok);
  EXPECT_EQ(anonymous.status, 401);
  EXPECT_EQ(anonymous.header("WWW-Authenticate"), "Bearer");
  EXPECT_NE(anonymous.body.find("\"UNAUTHENTICATED\""), std::string::npos);

  auto listed = Get("/api/jobs", Bearer(alice_));
  ASSERT_TRUE(listed.ok);
  ASSERT_EQ(listed.status, 200) << listed.body;
  const auto jobs = FromJson<v1::ListJobsResponse>(listed.body);
  ASSERT_EQ(jobs.jobs_size(), 2);
  EXPECT_EQ(jobs.jobs(0).id(), held.id());  // Newest first, as ListJobs.
  EXPECT_EQ(jobs.jobs(0).state(), v1::JOB_STATE_RUNNING);
  EXPECT_EQ(jobs.jobs(1).state(), v1::JOB_STATE_SUCCEEDED);

  // Bob: an empty list, and alice's jobs as missing as any.
  EXPECT_EQ(FromJson<v1::ListJobsResponse>(Get("/api/jobs", Bearer(bob_)).body).jobs_size(), 0);
  for (const std::string& path : {"/api/jobs/" + done.id(), "/api/jobs/" + done.id() + "/results/mesh.drc"}) {
    auto hidden = Get(path, Bearer(bob_));
    ASSERT_TRUE(hidden.ok);
    EXPECT_EQ(hidden.status, 404) << path;
    EXPECT_NE(hidden.body.find("no job with id '" + done.id() + "'"), std::string::npos) << hidden.body;
  }

  // Headers gRPC could not carry, and tokens that are not alice's.
  for (const std::string& authorization :
       {std::string("Basic YWxpY2U6eA=="), std::string("Bearer "), "Bearer " + std::string(5000, 'a'),
        std::string("Bearer a b"), "Bearer " + alice_ + "x"}) {
    auto refused = Get("/api/jobs", authorization);
    ASSERT_TRUE(refused.ok);
    EXPECT_EQ(refused.status, 401) << authorization.substr(0, 40);
  }

  auto job = Get("/api/jobs/" + done.id(), Bearer(alice_));
  ASSERT_TRUE(job.ok);
  EXPECT_EQ(FromJson<v1::Job>(job.body).statistics_size(), Connect(alice_).Get(done.id())->statistics_size());
  EXPECT_EQ(Get("/api/jobs/not-an-id", Bearer(alice_)).status, 400);
  EXPECT_EQ(Get("/api/jobs?limit=-7", Bearer(alice_)).status, 200);
  EXPECT_EQ(Get("/api/jobs?limit=many", Bearer(alice_)).status, 200);
  EXPECT_EQ(Get("/api/nothing", Bearer(alice_)).status, 404);
  auto posted = testing::HttpPost(gateway_->address(), "/api/jobs", Bearer(alice_), "{}");
  EXPECT_EQ(posted.status, 405);
  EXPECT_EQ(posted.header("Allow"), "GET, HEAD");
  auto methods = Get("/api/methods", Bearer(alice_));
  EXPECT_GT(FromJson<v1::ListMethodsResponse>(methods.body).methods_size(), 5);
}

TEST_F(HttpGatewayTest, AResultDownloadsAsOverGrpcAndACutDownloadHarmsNothing) {
  // A result of several gRPC chunks, written by a held job that is then let go.
  std::string big(3 << 20, '\0');
  for (size_t i = 0; i < big.size(); ++i) big[i] = static_cast<char>((i * 2654435761u) >> 13);
  latch_.WriteBeforeHolding("big.bin", big);
  const v1::Job done = Submit("apss", 500);
  latch_.WaitStarted(1);
  latch_.Release();
  ASSERT_EQ(Connect(alice_).Watch(done.id())->state(), v1::JOB_STATE_SUCCEEDED);
  auto expected = Connect(alice_).Fetch(done.id(), "big.bin");
  ASSERT_TRUE(expected.ok());
  ASSERT_EQ(*expected, big);

  auto whole = Get("/api/jobs/" + done.id() + "/results/big.bin", Bearer(alice_));
  ASSERT_TRUE(whole.ok);
  ASSERT_EQ(whole.status, 200);
  EXPECT_EQ(whole.body, big);
  EXPECT_EQ(whole.header("Content-Length"), std::to_string(big.size()));
  EXPECT_EQ(whole.header("Content-Type"), "application/octet-stream");
  EXPECT_EQ(Get("/api/jobs/" + done.id() + "/results/..%2fjobs.sqlite", Bearer(alice_)).status, 404);

  // Browsers that go away mid-download: each transfer stops, and the next is whole.
  for (int i = 0; i < 8; ++i) {
    size_t received = 0;
    auto cut = testing::HttpGet(gateway_->address(), "/api/jobs/" + done.id() + "/results/big.bin", Bearer(alice_),
                                [&](const char*, size_t n) {
                                  received += n;
                                  return received < (size_t{1} << 16);
                                });
    EXPECT_FALSE(cut.ok);
  }
  auto again = Get("/api/jobs/" + done.id() + "/results/big.bin", Bearer(alice_));
  ASSERT_TRUE(again.ok);
  EXPECT_EQ(again.body, big);
}

TEST_F(HttpGatewayTest, ThePageAndItsFilesCarryTheirTypesAndAStrictPolicy) {
  auto page = Get("/");
  ASSERT_TRUE(page.ok);
  EXPECT_EQ(page.status, 200);
  EXPECT_NE(page.header("Content-Security-Policy").find("default-src 'self'"), std::string::npos);
  EXPECT_EQ(page.header("X-Content-Type-Options"), "nosniff");
  if (WebAssets().empty()) GTEST_SKIP() << "built without the page (LSQSURF_WITH_WEB=OFF)";
  EXPECT_EQ(page.header("Content-Type"), "text/html; charset=utf-8");
  EXPECT_EQ(Get("/jobs/0123456789abcdef0123456789abcdef").body, page.body);
  for (const WebAsset& asset : WebAssets()) {
    auto served = Get(std::string(asset.path));
    ASSERT_TRUE(served.ok);
    EXPECT_EQ(served.status, 200) << asset.path;
    EXPECT_EQ(served.body, asset.bytes) << asset.path;
    EXPECT_EQ(served.header("Content-Type").rfind(std::string(asset.content_type), 0), 0u);
  }
  EXPECT_EQ(Get("/static/missing.js").status, 404);
  EXPECT_EQ(Get("/jobs/not-hex").status, 404);
}

}  // namespace
}  // namespace lsqsurf::server
