// Tokens, per-user isolation, quotas and TLS: a ReconstructionService in this process on a
// loopback port, reached through the real client library, with a token file and certificates
// the tests make themselves.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <sys/resource.h>

#include <filesystem>
#include <fstream>
#include <thread>

#include "client/client.h"
#include "server/server.h"
#include "server/tls.h"
#include "server/tokens.h"
#include "tests/latch_kind.h"
#include "tests/test_ca.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "tests/zlib_bomb.h"
#include "worker/io/draco_codec.h"
#include "worker/io/volume_codec.h"
#include "worker/volume/synthetic.h"

namespace lsqsurf::server {
namespace {

namespace fs = std::filesystem;

void WriteFile(const fs::path& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << text;
}

std::string ReadFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

std::string MakeToken(const fs::path& file, const std::string& name, Role role, int max_jobs = 0,
                      int64_t max_upload_mib = 0) {
  TokenEntry entry;
  entry.name = name;
  entry.role = role;
  entry.max_jobs = max_jobs;
  entry.max_upload_mib = max_upload_mib;
  auto token = AddToken(file.string(), entry);
  if (!token.ok()) throw std::runtime_error(std::string(token.status().message()));
  return *token;
}

TEST(TokenFileTest, TokensAreKeptOnlyAsSaltedHashesAndAuthenticateTheirHolder) {
  const fs::path dir = testing::FreshTestDir("lsqsurf-tokens");
  fs::create_directories(dir);
  const fs::path file = dir / "tokens";
  const std::string alice = MakeToken(file, "alice", Role::kUser, 3, 5);
  const std::string root = MakeToken(file, "root", Role::kAdmin);
  EXPECT_NE(alice, root);
  const std::string text = ReadFile(file);
  EXPECT_EQ(text.find(alice), std::string::npos);
  EXPECT_EQ(text.find(alice.substr(4)), std::string::npos);  // Nor the token without its prefix.
  EXPECT_EQ(fs::status(file).permissions() & fs::perms::all, fs::perms::owner_read | fs::perms::owner_write);
  TokenEntry again;
  again.name = "alice";
  EXPECT_EQ(AddToken(file.string(), again).status().code(), absl::StatusCode::kAlreadyExists);
  again.name = "a b";
  EXPECT_EQ(AddToken(file.string(), again).status().code(), absl::StatusCode::kInvalidArgument);

  auto table = TokenTable::Load(file.string());
  ASSERT_TRUE(table.ok()) << table.status();
  auto caller = (*table)->Authenticate("Bearer " + alice);
  ASSERT_TRUE(caller.ok()) << caller.status();
  EXPECT_EQ(caller->name, "alice");
  EXPECT_FALSE(caller->admin());
  EXPECT_EQ(caller->submitter.owner, "alice");
  EXPECT_EQ(caller->submitter.max_active_jobs, 3);
  EXPECT_EQ(caller->submitter.max_upload_bytes, 5 << 20);
  EXPECT_TRUE((*table)->Authenticate("Bearer " + root)->admin());
  std::string altered = alice;
  altered.back() = altered.back() == '0' ? '1' : '0';
  for (const std::string& wrong :
       std::vector<std::string>{"", "Bearer ", "Bearer " + alice + "x", "Basic " + alice, alice, "Bearer " + altered}) {
    const auto refused = (*table)->Authenticate(wrong);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kUnauthenticated) << wrong;
    EXPECT_EQ(refused.status().message().find(alice.substr(4)), std::string::npos);
  }

  // Revoked: refused after a reload; the others stay.
  ASSERT_TRUE(RevokeToken(file.string(), "alice").ok());
  EXPECT_EQ(RevokeToken(file.string(), "alice").code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE((*table)->Authenticate("Bearer " + alice).ok());  // Not reloaded yet.
  ASSERT_EQ(*(*table)->Reload(), 1u);
  EXPECT_EQ((*table)->Authenticate("Bearer " + alice).status().code(), absl::StatusCode::kUnauthenticated);
  EXPECT_TRUE((*table)->Authenticate("Bearer " + root).ok());
  fs::remove_all(dir);
}

TEST(TokenFileTest, ABrokenFileIsNamedByLineAndAReloadKeepsTheTokensInUse) {
  const fs::path dir = testing::FreshTestDir("lsqsurf-tokens");
  fs::create_directories(dir);
  const fs::path file = dir / "tokens";
  const std::string root = MakeToken(file, "root", Role::kAdmin);
  auto table = TokenTable::Load(file.string());
  ASSERT_TRUE(table.ok());
  const std::string good = ReadFile(file);
  WriteFile(file, good + "bob superuser 00 11\n");
  auto reloaded = (*table)->Reload();
  ASSERT_FALSE(reloaded.ok());
  EXPECT_NE(reloaded.status().message().find("tokens:4:"), std::string::npos) << reloaded.status();
  EXPECT_TRUE((*table)->Authenticate("Bearer " + root).ok());
  for (const std::string& bad : {std::string("bob user 00112233445566778899aabbccddeeff"),  // No hash.
                                 "bob user 0011 " + std::string(64, 'a'),                   // Short salt.
                                 "bob user 00112233445566778899aabbccddeeff " + std::string(64, 'a') + " max_cpu=3"}) {
    EXPECT_EQ(ParseTokens(bad, "f").status().code(), absl::StatusCode::kInvalidArgument) << bad;
  }
  const std::string line = "bob user 00112233445566778899aabbccddeeff " + std::string(64, 'a') + "\n";
  EXPECT_EQ(ParseTokens(line + line, "f").status().code(), absl::StatusCode::kInvalidArgument);  // Name twice.
  EXPECT_EQ(TokenTable::Load((dir / "missing").string()).status().code(), absl::StatusCode::kNotFound);
  fs::remove_all(dir);
}

// A job service (apss jobs held by a latch, iamls real) behind the gRPC service, with tokens
// and the given credentials.
class SecureServer {
 public:
  SecureServer(const fs::path& dir, const TokenTable* tokens, std::shared_ptr<grpc::ServerCredentials> credentials) {
    jobs::JobServiceOptions options;
    options.data_dir = dir.string();
    options.kind_overrides["apss"] = &latch_;
    options.max_queue = 8;
    auto jobs = jobs::JobService::Open(options);
    if (!jobs.ok()) throw std::runtime_error(std::string(jobs.status().message()));
    jobs_ = *std::move(jobs);
    ServerOptions server_options;
    server_options.credentials = std::move(credentials);
    server_options.tokens = tokens;
    auto server = Server::Start(*jobs_, server_options);
    if (!server.ok()) throw std::runtime_error(std::string(server.status().message()));
    server_ = *std::move(server);
  }
  ~SecureServer() {
    latch_.Release();
    server_.reset();  // Before the job service it serves.
    jobs_.reset();
  }
  std::string address() const { return server_->address(); }
  client::Client Connect(const std::string& token, client::ConnectOptions options = {}) const {
    options.token = token;
    return client::Client(address(), options);
  }
  testing::LatchKind& latch() { return latch_; }

 private:
  testing::LatchKind latch_;
  std::unique_ptr<jobs::JobService> jobs_;
  std::unique_ptr<Server> server_;
};

class IsolationTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-isolation");
    fs::create_directories(dir_);
    alice_ = MakeToken(dir_ / "tokens", "alice", Role::kUser, /*max_jobs=*/2, /*max_upload_mib=*/1);
    bob_ = MakeToken(dir_ / "tokens", "bob", Role::kUser);
    root_ = MakeToken(dir_ / "tokens", "root", Role::kAdmin);
    auto tokens = TokenTable::Load((dir_ / "tokens").string());
    ASSERT_TRUE(tokens.ok());
    tokens_ = *std::move(tokens);
    server_ = std::make_unique<SecureServer>(dir_ / "data", tokens_.get(), grpc::InsecureServerCredentials());
    auto cloud = io::EncodeDracoPointCloud(testing::SphereCloud(2000), {});
    ASSERT_TRUE(cloud.ok());
    cloud_ = *cloud;
  }
  void TearDown() override {
    server_.reset();
    fs::remove_all(dir_);
  }
  v1::JobSpec Spec(const std::string& method) {
    v1::JobSpec spec;
    EXPECT_TRUE(client::SetMethod(&spec, method).ok());
    return spec;
  }

  fs::path dir_;
  std::string alice_, bob_, root_, cloud_;
  std::unique_ptr<TokenTable> tokens_;
  std::unique_ptr<SecureServer> server_;
};

TEST_F(IsolationTest, AUserCannotSeeFetchRenderCancelOrDeleteAnothersJob) {
  client::Client alice = server_->Connect(alice_), bob = server_->Connect(bob_), root = server_->Connect(root_);
  auto done = alice.Submit(Spec("iamls"), cloud_);
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->owner(), "alice");
  ASSERT_EQ(alice.Watch(done->id())->state(), v1::JOB_STATE_SUCCEEDED);
  auto held = alice.Submit(Spec("apss"), cloud_);
  ASSERT_TRUE(held.ok()) << held.status();
  server_->latch().WaitStarted(1);

  // Another user's job answers exactly as a missing one does, for every rpc that names a job.
  const std::string missing = "0123456789abcdef";
  for (const std::string& id : {done->id(), held->id(), missing}) {
    SCOPED_TRACE(id);
    const std::string expected = "no job with id '" + id + "'";
    const auto expect_hidden = [&](const absl::Status& status) {
      EXPECT_EQ(status.code(), absl::StatusCode::kNotFound) << status;
      EXPECT_EQ(status.message(), expected);
    };
    expect_hidden(bob.Get(id).status());
    expect_hidden(bob.Watch(id).status());
    expect_hidden(bob.Fetch(id, "").status());
    expect_hidden(bob.Render(id, "", {}).status());
    expect_hidden(bob.Cancel(id).status());
    expect_hidden(bob.Delete(id));
  }
  auto bobs_list = bob.List(0);
  ASSERT_TRUE(bobs_list.ok());
  EXPECT_EQ(bobs_list->jobs_size(), 0);
  // Nothing bob did touched them.
  EXPECT_EQ(alice.Get(held->id())->state(), v1::JOB_STATE_RUNNING);
  auto mesh = alice.Fetch(done->id(), "");
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(io::DecodeDracoMesh(*mesh).ok());
  EXPECT_NE(alice.Render(done->id(), "", {}).status().code(), absl::StatusCode::kNotFound);

  // Bob's own job is his alone; the admin sees all three.
  auto bobs = bob.Submit(Spec("iamls"), cloud_);
  ASSERT_TRUE(bobs.ok());
  EXPECT_EQ(alice.Get(bobs->id()).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(alice.List(0)->jobs_size(), 2);
  EXPECT_EQ(root.List(0)->jobs_size(), 3);
  EXPECT_EQ(root.Get(bobs->id())->owner(), "bob");
  EXPECT_EQ(root.Fetch(done->id(), "").value_or(""), *mesh);
  ASSERT_TRUE(root.Cancel(held->id()).ok());
  EXPECT_EQ(alice.Watch(held->id())->state(), v1::JOB_STATE_CANCELLED);
  EXPECT_TRUE(alice.Delete(done->id()).ok());
}

// Jobs that read another job's results (csg operands, edit and probe sources) may name only
// jobs their submitter may see: another user's answers exactly as a missing id does, at once,
// and no job is made that could report on it.
// The peak resident memory of this process (server and client in one), bytes.
int64_t PeakResidentBytes() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return int64_t{usage.ru_maxrss} * 1024;
}

// A 4.2 MB cell stream that inflates to 4 GiB, sent through the server as a user's upload
// (the server once inflated such a stream whole, 4.2 GB, before any parsing). Declaring its true
// length, it is refused before inflating; declaring the length of its one cell, it is refused as
// corrupt at the first byte past it. Either costs an inflation window, and the server goes on.
TEST_F(IsolationTest, ACellStreamBombCostsTheServerItsWindowOnly) {
  client::Client bob = server_->Connect(bob_);
  volume::VolumeMesh mesh = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 4, 0.3, 2);
  volume::SampleField(mesh, volume::Franke3d());
  const std::vector<std::string> fields = {"franke"};
  const std::string bomb = testing::CellStreamBomb(uint64_t{4} << 30);
  ASSERT_LT(bomb.size(), size_t{5} << 20);
  // The same deflated bytes behind a header that declares the cell's 6 bytes only. The varint of
  // 4 GiB + 6 takes 5 bytes, that of 6 one.
  const std::string lying = "LQC1\x06" + bomb.substr(4 + 5);
  v1::JobSpec spec;
  spec.mutable_volume()->set_field("franke");
  const std::string vertices = *io::EncodeVolumeVertices(mesh, fields, {});
  const int64_t peak_before = PeakResidentBytes();
  auto too_long = bob.Submit(spec, vertices, {}, bomb);
  EXPECT_EQ(too_long.status().code(), absl::StatusCode::kResourceExhausted) << too_long.status();
  EXPECT_NE(too_long.status().message().find("cells: the cell stream declares"), std::string_view::npos)
      << too_long.status();
  auto corrupt = bob.Submit(spec, vertices, {}, lying);
  EXPECT_EQ(corrupt.status().code(), absl::StatusCode::kInvalidArgument) << corrupt.status();
  EXPECT_NE(corrupt.status().message().find("cells: the cell stream is corrupt"), std::string_view::npos)
      << corrupt.status();
  EXPECT_LT(PeakResidentBytes() - peak_before, int64_t{256} << 20);
  auto fine = bob.Submit(spec, vertices, {}, io::EncodeCellStream(mesh));
  EXPECT_TRUE(fine.ok()) << fine.status();
}

TEST_F(IsolationTest, AJobCannotReferToAnotherUsersJob) {
  client::Client alice = server_->Connect(alice_), bob = server_->Connect(bob_), root = server_->Connect(root_);
  v1::JobSpec pu;
  pu.mutable_pu();
  auto fitted = alice.Submit(pu, cloud_);
  ASSERT_TRUE(fitted.ok()) << fitted.status();
  volume::VolumeMesh mesh = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 5, 0.3, 2);
  volume::SampleField(mesh, volume::Franke3d());
  const std::vector<std::string> fields = {"franke"};
  v1::JobSpec volume_spec;
  volume_spec.mutable_volume()->set_field("franke");
  volume_spec.mutable_volume()->add_iso(0.4);
  auto field = alice.Submit(volume_spec, *io::EncodeVolumeVertices(mesh, fields, {}), {}, io::EncodeCellStream(mesh));
  ASSERT_TRUE(field.ok()) << field.status();
  ASSERT_EQ(alice.Watch(fitted->id())->state(), v1::JOB_STATE_SUCCEEDED);
  ASSERT_EQ(alice.Watch(field->id())->state(), v1::JOB_STATE_SUCCEEDED);

  const auto csg = [](const std::string& id) {
    v1::JobSpec spec;
    spec.mutable_csg()->set_expression("union(job:" + id + " sphere(r=0.1))");
    return spec;
  };
  const auto edit = [](const std::string& id) {
    v1::JobSpec spec;
    spec.mutable_edit()->set_source(id);
    spec.mutable_edit()->set_center_x(1.0);
    spec.mutable_edit()->set_radius(0.2);
    spec.mutable_edit()->set_degree(1);
    return spec;
  };
  const auto probe = [](const std::string& id) {
    v1::JobSpec spec;
    spec.mutable_probe()->set_source(id);
    spec.mutable_probe()->set_grid("4x4x4");
    return spec;
  };
  const std::string missing(32, 'a');
  struct Case {
    const char* kind;
    v1::JobSpec theirs, nobodys;
  };
  for (const Case& c : {Case{"csg", csg(fitted->id()), csg(missing)}, Case{"edit", edit(fitted->id()), edit(missing)},
                        Case{"probe", probe(field->id()), probe(missing)}}) {
    SCOPED_TRACE(c.kind);
    const absl::Status theirs = bob.Submit(c.theirs, "").status();
    const absl::Status nobodys = bob.Submit(c.nobodys, "").status();
    EXPECT_EQ(theirs.code(), absl::StatusCode::kNotFound) << theirs;
    EXPECT_EQ(nobodys.code(), absl::StatusCode::kNotFound) << nobodys;
    // Word for word the same, but for the id the caller gave.
    const std::string referenced = c.theirs.has_probe() ? field->id() : fitted->id();
    EXPECT_EQ(theirs.message(), "no job with id '" + referenced + "'");
    EXPECT_EQ(nobodys.message(), "no job with id '" + missing + "'");
  }
  EXPECT_EQ(bob.List(0)->jobs_size(), 0);  // Nothing was made that could fail with a telling error.

  // The owner and an admin may refer to it.
  for (client::Client* allowed : {&alice, &root}) {
    auto job = allowed->Submit(csg(fitted->id()), "");
    ASSERT_TRUE(job.ok()) << job.status();
    EXPECT_EQ(allowed->Watch(job->id())->state(), v1::JOB_STATE_SUCCEEDED);
    auto probed = allowed->Submit(probe(field->id()), "");
    ASSERT_TRUE(probed.ok()) << probed.status();
    EXPECT_EQ(allowed->Watch(probed->id())->state(), v1::JOB_STATE_SUCCEEDED);
  }
}

// An upload that began before its token was revoked is not accepted when it ends.
TEST_F(IsolationTest, AnUploadWhoseTokenIsRevokedMeanwhileIsRefusedAtItsEnd) {
  auto channel = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
  auto stub = v1::Reconstruction::NewStub(channel);
  grpc::ClientContext context;
  context.AddMetadata("authorization", "Bearer " + bob_);
  v1::Job response;
  auto writer = stub->SubmitJob(&context, &response);
  v1::SubmitJobRequest message;
  *message.mutable_spec() = Spec("iamls");
  ASSERT_TRUE(writer->Write(message));
  message.Clear();
  message.set_input_chunk(cloud_.substr(0, cloud_.size() / 2));
  ASSERT_TRUE(writer->Write(message));
  ASSERT_TRUE(RevokeToken((dir_ / "tokens").string(), "bob").ok());
  ASSERT_TRUE(tokens_->Reload().ok());
  message.set_input_chunk(cloud_.substr(cloud_.size() / 2));
  writer->Write(message);
  writer->WritesDone();
  const grpc::Status status = writer->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAUTHENTICATED) << status.error_message();
  EXPECT_EQ(server_->Connect(root_).List(0)->jobs_size(), 0);
}

TEST_F(IsolationTest, AMissingOrWrongTokenIsUnauthenticatedWhileHealthStaysOpen) {
  for (const std::string& token : {std::string(), std::string("lsq_not-a-token"), alice_ + "0"}) {
    client::Client c = server_->Connect(token);
    EXPECT_EQ(c.List(0).status().code(), absl::StatusCode::kUnauthenticated) << token;
    EXPECT_EQ(c.Submit(Spec("iamls"), cloud_).status().code(), absl::StatusCode::kUnauthenticated);
    EXPECT_EQ(c.GetServerInfo().status().code(), absl::StatusCode::kUnauthenticated);
    auto serving = c.Serving("", std::chrono::seconds(5));
    ASSERT_TRUE(serving.ok()) << serving.status();
    EXPECT_TRUE(*serving);
  }
  EXPECT_EQ(server_->Connect(bob_).List(0)->jobs_size(), 0);
}

TEST_F(IsolationTest, QuotasBoundJobsAndUploadsPerToken) {
  client::Client alice = server_->Connect(alice_), bob = server_->Connect(bob_);
  ASSERT_TRUE(alice.Submit(Spec("apss"), cloud_).ok());
  ASSERT_TRUE(alice.Submit(Spec("apss"), cloud_).ok());
  auto third = alice.Submit(Spec("apss"), cloud_);
  EXPECT_EQ(third.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(third.status().message().find("quota"), std::string::npos) << third.status();
  EXPECT_TRUE(bob.Submit(Spec("apss"), cloud_).ok());  // Bob has no limit.
  auto info = alice.GetServerInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_TRUE(info->requires_token());
  EXPECT_EQ(info->account().name(), "alice");
  EXPECT_EQ(info->account().active_jobs(), 2);
  EXPECT_EQ(info->account().max_jobs(), 2);
  EXPECT_EQ(info->account().stored_bytes(),
            2 * (static_cast<int64_t>(cloud_.size()) + jobs::ResultReserve(static_cast<int64_t>(cloud_.size()))));

  // More than alice's 1 MiB is refused while it streams in; bob may send it.
  const std::string big((size_t{3} << 19), 'x');
  auto refused = alice.Submit(Spec("iamls"), big);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.status().message().find("your quota"), std::string::npos) << refused.status();
  EXPECT_EQ(bob.Submit(Spec("iamls"), big).status().code(), absl::StatusCode::kInvalidArgument);  // Not Draco.
}

// TLS: a CA made here, the server's certificate for 127.0.0.1, clients trusting it or not.
class TlsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-tls");
    fs::create_directories(dir_);
    const testing::PemPair server = ca_.Issue("127.0.0.1");
    WriteFile(dir_ / "server.crt", server.cert);
    WriteFile(dir_ / "server.key", server.key);
    WriteFile(dir_ / "ca.crt", ca_.cert_pem());
    files_ = {(dir_ / "server.crt").string(), (dir_ / "server.key").string(), ""};
  }
  void TearDown() override {
    server_.reset();
    fs::remove_all(dir_);
  }
  void Start(const TlsFiles& files) {
    auto tls = ServerTls::Open(files, (dir_ / "staged").string());
    ASSERT_TRUE(tls.ok()) << tls.status();
    tls_ = *std::move(tls);
    server_ = std::make_unique<SecureServer>(dir_ / "data", nullptr, tls_->credentials());
  }
  client::ConnectOptions Trusting(const testing::TestCa& ca, const testing::PemPair& identity = {}) {
    client::ConnectOptions options;
    options.ca_pem = ca.cert_pem();
    options.cert_pem = identity.cert;
    options.key_pem = identity.key;
    return options;
  }

  fs::path dir_;
  testing::TestCa ca_{"lsqsurf test CA"};
  TlsFiles files_;
  std::unique_ptr<ServerTls> tls_;
  std::unique_ptr<SecureServer> server_;
};

TEST_F(TlsTest, ClientsThatTrustTheCaConnectAndOthersAreRefused) {
  Start(files_);
  auto info = server_->Connect("", Trusting(ca_)).GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  testing::TestCa stranger("another CA");
  EXPECT_EQ(server_->Connect("", Trusting(stranger)).GetServerInfo().status().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(server_->Connect("").GetServerInfo().status().code(), absl::StatusCode::kUnavailable);  // Plaintext.
  // A whole job over TLS.
  client::Client c = server_->Connect("", Trusting(ca_));
  v1::JobSpec spec;
  ASSERT_TRUE(client::SetMethod(&spec, "iamls").ok());
  auto job = c.Submit(spec, *io::EncodeDracoPointCloud(testing::SphereCloud(2000), {}));
  ASSERT_TRUE(job.ok()) << job.status();
  ASSERT_EQ(c.Watch(job->id())->state(), v1::JOB_STATE_SUCCEEDED);
  EXPECT_TRUE(io::DecodeDracoMesh(*c.Fetch(job->id(), "")).ok());
}

TEST_F(TlsTest, MutualTlsRefusesMissingForeignAndExpiredClientCertificates) {
  files_.client_ca = (dir_ / "ca.crt").string();
  Start(files_);
  EXPECT_TRUE(server_->Connect("", Trusting(ca_, ca_.Issue("alice"))).GetServerInfo().ok());
  testing::TestCa stranger("another CA");
  const std::vector<std::pair<const char*, testing::PemPair>> refused = {
      {"none", {}}, {"foreign", stranger.Issue("mallory")}, {"expired", ca_.Issue("alice", -10, -1)}};
  for (const auto& [what, identity] : refused) {
    EXPECT_EQ(server_->Connect("", Trusting(ca_, identity)).GetServerInfo().status().code(),
              absl::StatusCode::kUnavailable)
        << what;
  }
}

TEST_F(TlsTest, BadOrExpiredServerFilesAreRefusedWithTheReason) {
  const testing::PemPair expired = ca_.Issue("127.0.0.1", -10, -1), other = ca_.Issue("127.0.0.1");
  const testing::PemPair early = ca_.Issue("127.0.0.1", 2, 30);
  WriteFile(dir_ / "expired.crt", expired.cert);
  WriteFile(dir_ / "expired.key", expired.key);
  WriteFile(dir_ / "early.crt", early.cert);
  WriteFile(dir_ / "early.key", early.key);
  WriteFile(dir_ / "other.key", other.key);
  const std::string staged = (dir_ / "staged").string();
  const auto reason = [&](const TlsFiles& files) {
    return std::string(ServerTls::Open(files, staged).status().message());
  };
  EXPECT_NE(reason({(dir_ / "expired.crt").string(), (dir_ / "expired.key").string(), ""}).find("expired"),
            std::string::npos);
  EXPECT_NE(reason({(dir_ / "early.crt").string(), (dir_ / "early.key").string(), ""}).find("not valid yet"),
            std::string::npos);
  EXPECT_NE(reason({files_.cert, (dir_ / "other.key").string(), ""}).find("is not the key"), std::string::npos);
  EXPECT_NE(reason({files_.key, files_.key, ""}).find("no PEM certificate"), std::string::npos);
  EXPECT_NE(reason({files_.cert, files_.key, files_.key}).find("no PEM certificate"), std::string::npos);
  EXPECT_NE(reason({(dir_ / "missing.crt").string(), files_.key, ""}).find("cannot read"), std::string::npos);
}

TEST_F(TlsTest, AReloadServesTheRenewedCertificateAndRefusesABrokenOne) {
  Start(files_);
  ASSERT_TRUE(server_->Connect("", Trusting(ca_)).GetServerInfo().ok());
  // A broken renewal is refused; the certificate in use stays.
  WriteFile(dir_ / "server.key", "not a key");
  EXPECT_FALSE(tls_->Reload().ok());
  // Renewed by another CA: clients trusting only that one get in once the server has it.
  testing::TestCa renewed_ca("renewed CA");
  const testing::PemPair renewed = renewed_ca.Issue("127.0.0.1");
  WriteFile(dir_ / "server.crt", renewed.cert);
  WriteFile(dir_ / "server.key", renewed.key);
  ASSERT_TRUE(tls_->Reload().ok());
  // gRPC looks at the staged files every second; wait (bounded) for it.
  bool served = false;
  for (int attempt = 0; attempt < 100 && !served; ++attempt) {
    served = server_->Connect("", Trusting(renewed_ca)).GetServerInfo().ok();
    if (!served) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_TRUE(served);
  EXPECT_EQ(server_->Connect("", Trusting(ca_)).GetServerInfo().status().code(), absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace lsqsurf::server
