#include "worker/jobs/job_service.h"

#include <gtest/gtest.h>
#include <sqlite3.h>
#include <sys/mount.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <limits>
#include <mutex>
#include <set>

#include "absl/cleanup/cleanup.h"
#include "absl/strings/match.h"
#include "stb_image.h"
#include "tests/latch_kind.h"
#if LSQSURF_WITH_POSTGRESQL
#include "tests/postgres_cluster.h"
#endif
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/io/mesh_part.h"
#include "worker/jobs/job_admission.h"
#include "worker/jobs/job_retention.h"
#include "worker/jobs/method_registry.h"
#if LSQSURF_WITH_POSTGRESQL
#include "worker/jobs/store/postgres_store.h"
#endif
#include "worker/jobs/surface_job.h"
#include "worker/jobs/track_job.h"

namespace lsqsurf::jobs {
namespace {

std::string Encode(const core::PointCloud& cloud, int position_bits = 16) {
  io::DracoOptions options;
  options.position_bits = position_bits;
  auto bytes = io::EncodeDracoPointCloud(cloud, options);
  EXPECT_TRUE(bytes.ok());
  return bytes.ok() ? *bytes : std::string();
}

// A spec for `method` with the named parameters parsed from text, as the CLI gives them.
JobSpec Spec(const std::string& method, const std::map<std::string, std::string>& values = {}) {
  JobSpec spec;
  spec.method = method;
  auto defaults = DefaultParams(method);
  if (defaults.ok()) spec.params = *defaults;
  for (const auto& [name, text] : values) EXPECT_TRUE(spec.params.Parse(name, text).ok()) << name << "=" << text;
  return spec;
}

Uploads Input(std::string bytes) { return {{kInputUpload, std::move(bytes)}}; }

class JobServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-jobs");
    options_.data_dir = dir_.string();
  }
  void TearDown() override {
    latch_.Release();
    service_.reset();
    std::filesystem::remove_all(dir_);
  }
  JobService& Open() {
    service_.reset();
    auto s = JobService::Open(options_);
    EXPECT_TRUE(s.ok()) << s.status();
    service_ = *std::move(s);
    return *service_;
  }
  // iamls jobs run on the latch from now on (until the service is reopened without it).
  void HoldIamlsJobs() { options_.kind_overrides["iamls"] = &latch_; }
  // Waits until the job satisfies `done`; the job's own progress bounds the wait.
  JobRecord WaitUntil(const std::string& id, const std::function<bool(const JobRecord&)>& done) {
    auto r = service_->Get(id);
    while (r.ok() && !done(*r)) r = service_->WaitForChange(id, r->version, std::chrono::seconds(1));
    EXPECT_TRUE(r.ok());
    return r.ok() ? *r : JobRecord{};
  }
  JobRecord WaitTerminal(const std::string& id) {
    return WaitUntil(id, [](const JobRecord& r) { return IsTerminal(r.state); });
  }
  std::string ReadResult(const std::string& id, const std::string& name) {
    auto reader = service_->OpenResult(id, name);
    EXPECT_TRUE(reader.ok()) << reader.status();
    if (!reader.ok()) return {};
    std::string all;
    for (;;) {
      auto chunk = (*reader)->Next(1000);  // Small chunks: the reader must stitch them exactly.
      EXPECT_TRUE(chunk.ok());
      if (!chunk.ok() || chunk->empty()) break;
      all += *chunk;
    }
    EXPECT_EQ(static_cast<int64_t>(all.size()), (*reader)->size());
    return all;
  }

  std::filesystem::path dir_;
  JobServiceOptions options_;
  std::unique_ptr<JobService> service_;
  testing::LatchKind latch_;
};

double Statistic(const JobRecord& r, const std::string& name) {
  for (const auto& [n, v] : r.statistics) {
    if (n == name) return v;
  }
  ADD_FAILURE() << "no statistic " << name;
  return NAN;
}

TEST_F(JobServiceTest, EverySurfaceMethodReconstructsASphere) {
  JobService& s = Open();
  for (const MethodEntry& method : Methods()) {
    if (method.kind != &SurfaceJobKind()) continue;  // Track jobs: see the end-to-end test.
    auto job = s.Submit(Spec(method.info.name), Input(Encode(testing::SphereCloud(5000))));
    ASSERT_TRUE(job.ok()) << job.status();
    EXPECT_EQ(job->state, JobState::kQueued);
    const JobRecord done = WaitTerminal(job->id);
    ASSERT_EQ(done.state, JobState::kSucceeded) << method.info.name << ": " << done.error;
    auto mesh = io::DecodeDracoMesh(ReadResult(job->id, "mesh.drc"));
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    // The delivered mesh, merged by position as STL export does, is a closed sphere.
    const core::MeshTopology t = core::AnalyzeTopology(core::WeldByPosition(*mesh));
    EXPECT_TRUE(t.watertight()) << method.info.name;
    EXPECT_EQ(t.euler_characteristic(), 2) << method.info.name;
    EXPECT_NEAR(core::EnclosedVolume(*mesh) / (4.0 / 3.0 * M_PI), 1.0, 0.02) << method.info.name;
    // The statistics describe that delivered mesh.
    EXPECT_EQ(Statistic(done, "non_manifold_edges"), t.non_manifold_edges) << method.info.name;
    EXPECT_EQ(Statistic(done, "boundary_edges"), t.boundary_edges) << method.info.name;
    EXPECT_GE(Statistic(done, "delivered_position_bits"), 16) << method.info.name;
    // The per-vertex scalars in the order the method's table names them: the job page reads them
    // by position (Draco unique ids 2, 3, ... after position and normal).
    std::vector<std::string> scalars;
    for (const core::ScalarAttribute& a : mesh->vertex_attributes) scalars.push_back(a.name);
    EXPECT_EQ(scalars, method.info.attributes) << method.info.name;
  }
}

// An engine that runs a stage again (PU's topology fallback extracts the whole surface anew)
// reports a smaller fraction than before; what watchers see does not go back.
TEST_F(JobServiceTest, ProgressNeverGoesBackwards) {
  latch_.ReportBeforeHolding({{"extracting surface", 0.9}, {"extracting surface without finer leaves", 0.5}});
  HoldIamlsJobs();
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok());
  latch_.WaitStarted(1);  // Both reported, the job held running.
  auto held = s.Get(job->id);
  ASSERT_TRUE(held.ok());
  EXPECT_EQ(held->stage, "extracting surface without finer leaves");
  EXPECT_EQ(held->progress, 0.9);
  latch_.Release();
  EXPECT_EQ(WaitTerminal(job->id).state, JobState::kSucceeded);
}

TEST_F(JobServiceTest, EstimatesMissingNormalsByDefault) {
  JobService& s = Open();
  core::PointCloud cloud = testing::SphereCloud(4000);
  cloud.normals.clear();
  auto job = s.Submit(Spec("iamls"), Input(Encode(cloud)));
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(WaitTerminal(job->id).state, JobState::kSucceeded);
}

TEST_F(JobServiceTest, RejectsBadInputWithTheRightCode) {
  options_.max_points = 5000;
  JobService& s = Open();
  const std::string good = Encode(testing::SphereCloud(1000));
  core::PointCloud nan_cloud = testing::SphereCloud(1000);
  nan_cloud.positions[17].y() = std::numeric_limits<float>::quiet_NaN();
  core::PointCloud no_normals = testing::SphereCloud(1000);
  no_normals.normals.clear();
  core::PointCloud long_normals = testing::SphereCloud(1000);
  for (auto& n : long_normals.normals) n *= 3.0f;
  core::TriangleMesh tetrahedron;
  tetrahedron.vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
  tetrahedron.faces = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
  auto mesh_upload = io::EncodeDracoMesh(tetrahedron, {});
  ASSERT_TRUE(mesh_upload.ok());
  JobSpec far_epsilon = Spec("iamls");
  far_epsilon.params.Mutable<IamlsJobParams>()->fit.epsilon = 9;
  JobSpec negative_noise = Spec("pu");
  negative_noise.params.Mutable<PuJobParams>()->fit.noise_level = -0.5;
  JobSpec bad_bits = Spec("iamls");
  bad_bits.mesh_position_bits = 40;
  struct Case {
    const char* what;
    JobSpec spec;
    Uploads uploads;
    absl::StatusCode code;
    const char* fragment;
  } cases[] = {
      {"empty upload", Spec("iamls"), Input(""), absl::StatusCode::kInvalidArgument, "no input"},
      {"truncated Draco", Spec("iamls"), Input(good.substr(0, good.size() / 2)), absl::StatusCode::kInvalidArgument,
       "Draco"},
      {"not Draco", Spec("iamls"), Input("hello"), absl::StatusCode::kInvalidArgument, "Draco"},
      {"a mesh, not a cloud", Spec("iamls"), Input(*mesh_upload), absl::StatusCode::kInvalidArgument, "triangle mesh"},
      {"NaN", Spec("iamls"), Input(Encode(nan_cloud, /*lossless*/ 0)), absl::StatusCode::kInvalidArgument, "NaN"},
      {"non-unit normals", Spec("iamls"), Input(Encode(long_normals)), absl::StatusCode::kInvalidArgument, "length"},
      {"unknown method", Spec("poisson"), Input(good), absl::StatusCode::kInvalidArgument, "available: iamls"},
      {"out of range", far_epsilon, Input(good), absl::StatusCode::kInvalidArgument, "epsilon=9 is out of range"},
      {"noise below zero", negative_noise, Input(good), absl::StatusCode::kInvalidArgument, "noise_level"},
      {"Draco bits", bad_bits, Input(good), absl::StatusCode::kInvalidArgument, "mesh_position_bits=40"},
      {"no normals, no estimation", Spec("iamls", {{"estimate_normals", "false"}}), Input(Encode(no_normals)),
       absl::StatusCode::kInvalidArgument, "no normals"},
      {"too many points", Spec("iamls"), Input(Encode(testing::SphereCloud(6000))),
       absl::StatusCode::kResourceExhausted, "at most 5000"},
      {"velocity for a surface",
       Spec("iamls"),
       {{kInputUpload, good}, {kVelocityUpload, "# vtk"}},
       absl::StatusCode::kInvalidArgument,
       "no 'velocity' upload"},
      {"user field, no grid",
       Spec("track", {{"interface", "sphere"}, {"field", "uploaded"}}),
       {},
       absl::StatusCode::kInvalidArgument,
       "none was uploaded"},
      {"grid without a user field",
       Spec("track"),
       {{kVelocityUpload, "# vtk DataFile Version 3.0\n"}},
       absl::StatusCode::kInvalidArgument,
       "only field=uploaded uses one"},
      {"grid not VTK",
       Spec("track", {{"field", "uploaded"}}),
       {{kVelocityUpload, "P3 2 2"}},
       absl::StatusCode::kInvalidArgument,
       "not a legacy VTK file"},
  };
  for (const Case& c : cases) {
    auto r = s.Submit(c.spec, c.uploads);
    ASSERT_FALSE(r.ok()) << c.what << " was accepted";
    EXPECT_EQ(r.status().code(), c.code) << c.what << ": " << r.status();
    EXPECT_NE(std::string(r.status().message()).find(c.fragment), std::string::npos) << c.what << ": " << r.status();
  }
  EXPECT_TRUE(s.List().empty());  // Nothing half-accepted.
}

TEST_F(JobServiceTest, FullQueueIsRefusedAndQueuedJobsCancelAtOnce) {
  options_.max_queue = 1;
  HoldIamlsJobs();
  JobService& s = Open();
  const Uploads input = Input(Encode(testing::SphereCloud(1000)));
  auto first = s.Submit(Spec("iamls"), input);
  ASSERT_TRUE(first.ok());
  latch_.WaitStarted(1);  // Out of the queue, held running.
  auto second = s.Submit(Spec("iamls"), input);
  ASSERT_TRUE(second.ok()) << second.status();
  auto third = s.Submit(Spec("iamls"), input);
  EXPECT_EQ(third.status().code(), absl::StatusCode::kResourceExhausted);

  auto cancelled = s.Cancel(second->id);
  ASSERT_TRUE(cancelled.ok());
  EXPECT_EQ(cancelled->state, JobState::kCancelled);  // Queued: cancelled at once.
  EXPECT_TRUE(s.Submit(Spec("iamls"), input).ok());   // Its place in the queue is free again.
}

TEST_F(JobServiceTest, RunningJobsCancelOnlyThroughTheirEngine) {
  HoldIamlsJobs();
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok());
  latch_.WaitStarted(1);
  EXPECT_EQ(s.retention().Delete(job->id).code(), absl::StatusCode::kFailedPrecondition);  // Not while running.
  auto requested = s.Cancel(job->id);
  ASSERT_TRUE(requested.ok());
  EXPECT_EQ(requested->state, JobState::kRunning);  // CANCELLED follows when the engine stops.
  const JobRecord stopped = WaitTerminal(job->id);
  EXPECT_EQ(stopped.state, JobState::kCancelled);
  EXPECT_EQ(s.Cancel(job->id).status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(s.OpenResult(job->id, "").status().code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(s.retention().Delete(job->id).ok());
  EXPECT_EQ(s.Get(job->id).status().code(), absl::StatusCode::kNotFound);
  EXPECT_FALSE(std::filesystem::exists(dir_ / "jobs" / job->id));
}

TEST_F(JobServiceTest, ReleasedJobsSucceedWithTheirArtifacts) {
  HoldIamlsJobs();
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok());
  latch_.WaitStarted(1);
  latch_.Release();
  const JobRecord done = WaitTerminal(job->id);
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_EQ(done.results, std::vector<std::string>{"held.txt"});
  EXPECT_EQ(ReadResult(job->id, ""), "released");  // The first result by default.
  EXPECT_EQ(s.OpenResult(job->id, "mesh.drc").status().code(), absl::StatusCode::kNotFound);
}

TEST_F(JobServiceTest, QuotasHoldPerOwnerAndFinishedJobsCountTheirResults) {
  HoldIamlsJobs();
  JobService& s = Open();
  const Uploads input = Input(Encode(testing::SphereCloud(1000)));
  const auto upload = static_cast<int64_t>(input.at(kInputUpload).size());
  Submitter alice{"alice", /*max_active_jobs=*/1, /*max_stored_bytes=*/4 * upload, /*max_upload_bytes=*/0};
  auto first = s.Submit(Spec("iamls"), input, alice);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->owner, "alice");
  EXPECT_EQ(first->stored_bytes, upload + ResultReserve(upload));  // Its results are reserved for.
  auto second = s.Submit(Spec("iamls"), input, alice);
  EXPECT_EQ(second.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(second.status().message().find("queued or running"), std::string::npos) << second.status();
  EXPECT_TRUE(s.Submit(Spec("iamls"), input, Submitter{"bob", 1, 0, 0}).ok());  // Others are not held back.

  // Once it ends, the job no longer counts as active, but what it keeps counts against the bytes.
  latch_.WaitStarted(1);
  latch_.Release();
  const JobRecord done = WaitTerminal(first->id);
  EXPECT_EQ(done.stored_bytes, upload + static_cast<int64_t>(std::string("released").size()));
  EXPECT_EQ(s.admission().UsageOf("alice").active_jobs, 0);
  EXPECT_EQ(s.admission().UsageOf("alice").stored_bytes, done.stored_bytes);
  auto third = s.Submit(Spec("iamls"), input, alice);
  ASSERT_TRUE(third.ok()) << third.status();
  ASSERT_EQ(WaitTerminal(third->id).state, JobState::kSucceeded);
  auto fourth = s.Submit(Spec("iamls"), input, alice);  // 2 jobs kept + this upload and reserve > 4 uploads.
  EXPECT_EQ(fourth.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(fourth.status().message().find("delete finished jobs"), std::string::npos) << fourth.status();
  ASSERT_TRUE(s.retention().Delete(first->id).ok());
  auto fifth = s.Submit(Spec("iamls"), input, alice);
  ASSERT_TRUE(fifth.ok()) << fifth.status();
  ASSERT_EQ(WaitTerminal(fifth->id).state, JobState::kSucceeded);
  // The upload limit: the submitter's when lower than the server's.
  alice.max_upload_bytes = upload - 1;
  EXPECT_EQ(s.admission().MaxUploadBytes(alice), upload - 1);
  EXPECT_EQ(s.Submit(Spec("iamls"), input, alice).status().code(), absl::StatusCode::kResourceExhausted);
  // Owners survive a restart.
  const int64_t kept = s.admission().UsageOf("alice").stored_bytes;
  JobService& reopened = Open();
  EXPECT_EQ(reopened.Get(third->id)->owner, "alice");
  EXPECT_EQ(reopened.admission().UsageOf("alice").stored_bytes, kept);
}

// Writes one artifact of a given size, then ends as told: succeeded, failed, or held until it is
// cancelled (with a latch the test waits on: the artifact is written by then).
class WritingKind final : public JobKind {
 public:
  enum class End { kSucceed, kFail, kHoldUntilCancelled };
  WritingKind(int64_t bytes, End end) : bytes_(bytes), end_(end) {}
  std::string_view name() const override { return "writing"; }
  std::vector<MethodInfo> Methods() const override { return {}; }
  absl::StatusOr<CheckedInput> CheckUploads(const JobSpec&, const Uploads&, const InputLimits&) const override {
    return CheckedInput{1, nullptr, {}};
  }
  absl::StatusOr<Statistics> Run(const JobSpec&, const Uploads&, RunEnvironment& env) const override {
    const absl::Status written = env.sink.Write("big.bin", std::string(static_cast<size_t>(bytes_), 'x'));
    {
      std::lock_guard lock(mutex_);
      ran_ = true;
      changed_.notify_all();
    }
    if (!written.ok()) return written;
    if (end_ == End::kFail) return absl::InternalError("failed on purpose");
    while (end_ == End::kHoldUntilCancelled && !env.context.IsCancelled()) {
      std::unique_lock lock(mutex_);
      changed_.wait_for(lock, std::chrono::milliseconds(5));
    }
    if (env.context.IsCancelled()) return absl::CancelledError("cancelled");
    return Statistics{{"written", static_cast<double>(bytes_)}};
  }
  void WaitRan() const {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return ran_; });
  }

 private:
  int64_t bytes_;
  End end_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  mutable bool ran_ = false;
};

// Fails quoting what it was given, as a parser quotes a bad expression.
class QuotingKind final : public JobKind {
 public:
  std::string_view name() const override { return "quoting"; }
  std::vector<MethodInfo> Methods() const override { return {}; }
  absl::StatusOr<CheckedInput> CheckUploads(const JobSpec&, const Uploads&, const InputLimits&) const override {
    return CheckedInput{1, nullptr, {}};
  }
  absl::StatusOr<Statistics> Run(const JobSpec&, const Uploads&, RunEnvironment&) const override {
    return absl::InvalidArgumentError("cannot read 'x\n[2026-12-01 00:00:00.000] [info] [job 0] succeeded" +
                                      std::string(20000, 'y') + "'");
  }
};

// A failure's reason reaches the record (and the log) bounded and without the line break that
// would forge a log line.
TEST_F(JobServiceTest, AFailuresQuotedTextIsBoundedAndEscaped) {
  const QuotingKind quoting;
  options_.kind_overrides["iamls"] = &quoting;
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(100))), {});
  ASSERT_TRUE(job.ok()) << job.status();
  const JobRecord done = WaitTerminal(job->id);
  EXPECT_EQ(done.state, JobState::kFailed);
  EXPECT_EQ(done.error.find('\n'), std::string::npos);
  EXPECT_NE(done.error.find("x\\x0a[2026"), std::string::npos) << done.error.substr(0, 80);
  EXPECT_LT(done.error.size(), 4200u);
}

// Text parameters past a small spec's size are stored bytes like an upload: a user cannot fill
// the store with 60 KiB parameters of jobs that fail at once (2,000 of them once grew the job
// database by 245 MB while every quota read 0).
TEST_F(JobServiceTest, LargeTextParametersCountAsStoredBytes) {
  const QuotingKind failing;
  options_.kind_overrides["volume"] = &failing;
  JobService& s = Open();
  const Uploads input = Input(Encode(testing::SphereCloud(100)));
  const auto upload = static_cast<int64_t>(input.at(kInputUpload).size());
  const JobSpec spec = Spec("volume", {{"field", "f"}, {"color_by", std::string(60 << 10, 'c')}});
  const int64_t text = SpecBytes(spec);
  EXPECT_GT(text, (60 << 10) - kFreeSpecBytes - 1);
  EXPECT_EQ(SpecBytes(Spec("iamls")), 0);  // Small specs cost nothing.
  const int64_t quota = 3 << 16;
  const Submitter alice{"alice", /*max_active_jobs=*/0, /*max_stored_bytes=*/quota, /*max_upload_bytes=*/0};
  // Each failed job keeps its upload and its text; the next is admitted with a reserve as well.
  int64_t expected = 0;
  while (expected * (upload + text) + 2 * upload + text <= quota) ++expected;
  int accepted = 0;
  absl::Status refused;
  for (int i = 0; i < 10 && refused.ok(); ++i) {
    auto job = s.Submit(spec, input, alice);
    if (!job.ok()) {
      refused = job.status();
      break;
    }
    ++accepted;
    const JobRecord done = WaitTerminal(job->id);
    EXPECT_EQ(done.state, JobState::kFailed);
    EXPECT_EQ(done.stored_bytes, upload + text);
  }
  EXPECT_EQ(accepted, expected);
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted) << refused;
  EXPECT_NE(refused.message().find("quota"), std::string::npos) << refused;
  EXPECT_EQ(s.admission().UsageOf("alice").stored_bytes, accepted * (upload + text));
}

// A job's results are held to its owner's stored-bytes quota as they are written (not only its
// upload at submission), and what a failed or cancelled job wrote counts as stored.
TEST_F(JobServiceTest, ResultsAreHeldToTheQuotaAndEndedJobsCountWhatTheyWrote) {
  const Uploads input = Input(Encode(testing::SphereCloud(1000)));
  const auto upload = static_cast<int64_t>(input.at(kInputUpload).size());
  const WritingKind too_big(10 * upload, WritingKind::End::kSucceed);
  const WritingKind failing(upload, WritingKind::End::kFail);
  const WritingKind held(upload, WritingKind::End::kHoldUntilCancelled);
  options_.kind_overrides["iamls"] = &too_big;
  options_.kind_overrides["apss"] = &failing;
  options_.kind_overrides["aamls"] = &held;
  JobService& s = Open();
  const Submitter alice{"alice", /*max_active_jobs=*/0, /*max_stored_bytes=*/5 * upload, /*max_upload_bytes=*/0};

  auto big = s.Submit(Spec("iamls"), input, alice);
  ASSERT_TRUE(big.ok()) << big.status();
  const JobRecord refused = WaitTerminal(big->id);
  EXPECT_EQ(refused.state, JobState::kFailed);
  EXPECT_NE(refused.error.find("past your quota"), std::string::npos) << refused.error;
  EXPECT_EQ(refused.stored_bytes, upload);  // Nothing was written.

  auto failed = s.Submit(Spec("apss"), input, alice);
  ASSERT_TRUE(failed.ok()) << failed.status();
  const JobRecord failed_done = WaitTerminal(failed->id);
  EXPECT_EQ(failed_done.state, JobState::kFailed);
  EXPECT_EQ(failed_done.stored_bytes, 2 * upload);

  auto cancelled = s.Submit(Spec("aamls"), input, alice);
  ASSERT_TRUE(cancelled.ok()) << cancelled.status();
  held.WaitRan();
  ASSERT_TRUE(s.Cancel(cancelled->id).ok());
  const JobRecord cancelled_done = WaitTerminal(cancelled->id);
  EXPECT_EQ(cancelled_done.state, JobState::kCancelled);
  EXPECT_EQ(cancelled_done.stored_bytes, 2 * upload);
  EXPECT_EQ(s.admission().UsageOf("alice").stored_bytes, 5 * upload);
  EXPECT_EQ(s.admission().StoredBytes(), 5 * upload);  // The server's own limit sees them as well.
  // The quota is full: nothing more is accepted until jobs are deleted.
  EXPECT_EQ(s.Submit(Spec("apss"), input, alice).status().code(), absl::StatusCode::kResourceExhausted);
}

// A named user may fill at most half of the queue: others still get in.
TEST_F(JobServiceTest, OneUserCannotFillTheQueue) {
  HoldIamlsJobs();
  options_.max_queue = 4;
  JobService& s = Open();
  const Uploads input = Input(Encode(testing::SphereCloud(1000)));
  const Submitter alice{"alice", 0, 0, 0}, bob{"bob", 0, 0, 0};
  ASSERT_TRUE(s.Submit(Spec("iamls"), input, alice).ok());
  latch_.WaitStarted(1);  // Running, no longer queued.
  ASSERT_TRUE(s.Submit(Spec("iamls"), input, alice).ok());
  ASSERT_TRUE(s.Submit(Spec("iamls"), input, alice).ok());
  const absl::Status third = s.Submit(Spec("iamls"), input, alice).status();
  EXPECT_EQ(third.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(third.message().find("half of this server's queue"), std::string::npos) << third;
  EXPECT_TRUE(s.Submit(Spec("iamls"), input, bob).ok());
  EXPECT_TRUE(s.Submit(Spec("iamls"), input, bob).ok());
  EXPECT_EQ(s.Submit(Spec("iamls"), input, bob).status().code(), absl::StatusCode::kResourceExhausted);  // Full.
}

// Jobs whose parameters would take more memory than a job may are refused at submission, saying
// what to change; those whose extraction grows past it stop there rather than grow on.
TEST_F(JobServiceTest, AJobThatWouldTakeMoreMemoryThanAllowedIsRefusedOrStopped) {
  options_.max_job_memory = int64_t{64} << 20;
  JobService& s = Open();
  const Uploads input = Input(Encode(testing::SphereCloud(20000)));
  // A hundred times the vertices a point of the default: gigabytes for 20k points.
  const absl::Status fine = s.Submit(Spec("iamls", {{"cell_size", "0.1"}}), input).status();
  EXPECT_EQ(fine.code(), absl::StatusCode::kResourceExhausted) << fine;
  EXPECT_NE(fine.message().find("raise cell_size"), std::string::npos) << fine;
  EXPECT_NE(fine.message().find("64 MiB a job may take"), std::string::npos) << fine;
  // So is an explicit spacing far below the points' own (the surface would need as many cells).
  EXPECT_EQ(s.Submit(Spec("ramls", {{"spacing", "1e-6"}}), input).status().code(),
            absl::StatusCode::kResourceExhausted);
  // A front allowed to grow past what memory holds.
  const absl::Status front = s.Submit(Spec("track", {{"max_points", "50000000"}}), {}).status();
  EXPECT_EQ(front.code(), absl::StatusCode::kResourceExhausted) << front;
  EXPECT_NE(front.message().find("lower max_points"), std::string::npos) << front;
  EXPECT_TRUE(s.List().empty());
  // The defaults fit.
  auto job = s.Submit(Spec("iamls"), input);
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(WaitTerminal(job->id).state, JobState::kSucceeded);
}

TEST_F(JobServiceTest, AnExtractionPastTheJobsMemoryStops) {
  // PU's adaptive cells make its estimate low; the extraction holds the line: 4 MiB is 2048 leaves.
  options_.max_job_memory = int64_t{4} << 20;
  JobService& s = Open();
  auto job = s.Submit(Spec("pu", {{"cell_size", "0.5"}}), Input(Encode(testing::SphereCloud(2000))));
  ASSERT_TRUE(job.ok()) << job.status();
  const JobRecord done = WaitTerminal(job->id);
  EXPECT_EQ(done.state, JobState::kFailed);
  EXPECT_NE(done.error.find("raise cell_size"), std::string::npos) << done.error;
  // With the memory it needs, the same job succeeds.
  options_.max_job_memory = 0;
  JobService& unbounded = Open();
  auto again = unbounded.Submit(Spec("pu", {{"cell_size", "0.5"}}), Input(Encode(testing::SphereCloud(2000))));
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(WaitTerminal(again->id).state, JobState::kSucceeded);
}

TEST_F(JobServiceTest, RetentionDeletesTheOldestFinishedJobsAndNeverAQueuedOrRunningOne) {
  HoldIamlsJobs();
  options_.sweep_interval = std::chrono::hours(1);  // The test sweeps by hand.
  JobService* s = &Open();
  const Uploads input = Input(std::string(1000, 'x'));  // The latch takes any bytes.
  std::vector<std::string> finished;
  for (int i = 0; i < 3; ++i) {
    auto job = s->Submit(Spec("iamls"), input);
    ASSERT_TRUE(job.ok()) << job.status();
    ASSERT_TRUE(s->Cancel(job->id).ok());  // Queued or just started: it ends cancelled.
    ASSERT_EQ(WaitTerminal(job->id).state, JobState::kCancelled);
    finished.push_back(job->id);
  }
  const int started = latch_.started();
  auto running = s->Submit(Spec("iamls"), input);
  auto queued = s->Submit(Spec("iamls"), input);
  ASSERT_TRUE(running.ok() && queued.ok());
  latch_.WaitStarted(started + 1);
  const int64_t kept = s->admission().StoredBytes();
  EXPECT_EQ(kept, 3 * 1000 + 2 * (1000 + ResultReserve(1000)));  // The two unfinished reserve for results.
  const int64_t now = s->Get(finished.back())->updated_ms;
  EXPECT_EQ(s->retention().SweepFinished(now + 1), 0);  // No limits set: nothing goes.

  // Over the byte limit: the oldest finished job goes first, and only as many as needed.
  options_.max_store_bytes = kept - 1;
  s = &Open();
  EXPECT_EQ(s->retention().SweepFinished(now), 1);
  EXPECT_EQ(s->Get(finished[0]).status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(s->Get(finished[1]).ok());
  // Past their age every finished job goes; the queued and running ones stay whatever the limit.
  options_.retain = std::chrono::hours(48);
  options_.max_store_bytes = 1;
  s = &Open();
  EXPECT_EQ(s->retention().SweepFinished(now + int64_t{49} * 3600 * 1000), 2);
  EXPECT_FALSE(IsTerminal(s->Get(running->id)->state));
  EXPECT_FALSE(IsTerminal(s->Get(queued->id)->state));
  EXPECT_FALSE(std::filesystem::exists(dir_ / "jobs" / finished[1]));
  EXPECT_TRUE(std::filesystem::exists(dir_ / "jobs" / queued->id));
  // Nothing finished is left to make room: submissions are refused, saying why.
  auto refused = s->Submit(Spec("iamls"), input);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.status().message().find("store is full"), std::string::npos) << refused.status();
}

TEST_F(JobServiceTest, FilesOfJobsNeverStoredAreRemovedAtStart) {
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls", {{"iterations", "1"}}), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok());
  ASSERT_EQ(WaitTerminal(job->id).state, JobState::kSucceeded);
  service_.reset();
  // What a crash between an upload and its record, or inside a write, leaves behind.
  const auto jobs = dir_ / "jobs";
  std::filesystem::create_directories(jobs / "00000000deadbeef");
  std::ofstream(jobs / "00000000deadbeef" / "input.drc") << "never stored";
  std::ofstream(jobs / job->id / "mesh.drc.tmp.12345") << "cut short";
  JobService& reopened = Open();
  EXPECT_FALSE(std::filesystem::exists(jobs / "00000000deadbeef"));
  EXPECT_FALSE(std::filesystem::exists(jobs / job->id / "mesh.drc.tmp.12345"));
  EXPECT_TRUE(reopened.OpenResult(job->id, "mesh.drc").ok());  // The stored job keeps its files.
}

TEST_F(JobServiceTest, ANearlyFullDiskRefusesSubmissions) {
  options_.min_free_bytes = int64_t{1} << 60;  // More than any disk has.
  JobService& s = Open();
  auto refused = s.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.status().message().find("disk is nearly full"), std::string::npos) << refused.status();
  EXPECT_TRUE(s.List().empty());
}

// Counts the reads of each blob name, storing through a local folder.
class CountingBlobStore final : public BlobStore {
 public:
  explicit CountingBlobStore(std::unique_ptr<BlobStore> inner) : inner_(std::move(inner)) {}
  absl::Status Put(const std::string& id, std::string_view name, std::string_view bytes) override {
    return inner_->Put(id, name, bytes);
  }
  absl::StatusOr<std::unique_ptr<BlobReader>> Open(const std::string& id, std::string_view name) const override {
    std::lock_guard lock(mutex_);
    ++opened_[std::string(name)];
    return inner_->Open(id, name);
  }
  bool Exists(const std::string& id, std::string_view name) const override { return inner_->Exists(id, name); }
  absl::Status Remove(const std::string& id, std::string_view name) override { return inner_->Remove(id, name); }
  absl::Status RemoveJob(const std::string& id) override { return inner_->RemoveJob(id); }
  int opened(const std::string& name) const {
    std::lock_guard lock(mutex_);
    auto it = opened_.find(name);
    return it == opened_.end() ? 0 : it->second;
  }

 private:
  std::unique_ptr<BlobStore> inner_;
  mutable std::mutex mutex_;
  mutable std::map<std::string, int> opened_;
};

// A data directory on a 2 MiB tmpfs (root only): uploads until the disk is full are refused with
// RESOURCE_EXHAUSTED, and what was stored before stays whole, before and after a restart.
TEST_F(JobServiceTest, AFullDiskRefusesNewJobsAndCorruptsNothingStored) {
  std::filesystem::create_directories(dir_);
  if (::mount("tmpfs", dir_.c_str(), "tmpfs", 0, "size=2m") != 0) {
    GTEST_SKIP() << "cannot mount a tmpfs here (needs root): " << std::strerror(errno);
  }
  const absl::Cleanup unmount = [&] {
    service_.reset();
    EXPECT_EQ(::umount(dir_.c_str()), 0) << std::strerror(errno);
  };
  HoldIamlsJobs();
  // A store that cannot tell its free space: the disk itself says no, at the write.
  auto local = LocalDirBlobStore::Open((dir_ / "jobs").string());
  ASSERT_TRUE(local.ok());
  options_.blobs = std::make_shared<CountingBlobStore>(*std::move(local));
  std::map<std::string, std::string> stored;
  absl::Status refusal;
  {
    JobService& s = Open();
    for (int i = 0; i < 20 && refusal.ok(); ++i) {
      std::string bytes(300'000, static_cast<char>('a' + i));
      auto job = s.Submit(Spec("iamls"), Input(bytes));
      if (job.ok()) {
        stored[job->id] = bytes;
      } else {
        refusal = job.status();
      }
    }
    EXPECT_EQ(refusal.code(), absl::StatusCode::kResourceExhausted) << refusal;
    EXPECT_NE(refusal.message().find("disk is full"), std::string::npos) << refusal;
    EXPECT_GE(stored.size(), 3u);
    EXPECT_EQ(s.List().size(), stored.size());
  }
  service_.reset();
  auto blobs = LocalDirBlobStore::Open((dir_ / "jobs").string());
  ASSERT_TRUE(blobs.ok());
  for (const auto& [id, bytes] : stored) EXPECT_EQ((*blobs)->Read(id, "input.drc").value_or(""), bytes) << id;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(dir_ / "jobs")) {
    EXPECT_EQ(entry.path().filename().string().find(".tmp."), std::string::npos) << entry.path();
  }
  // With the files' own store, which knows its free space, the next upload is refused up front.
  options_.blobs = nullptr;
  options_.min_free_bytes = 0;
  JobService& reopened = Open();
  EXPECT_EQ(reopened.List().size(), stored.size());
  auto refused = reopened.Submit(Spec("iamls"), Input(std::string(300'000, 'z')));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.status().message().find("nearly full"), std::string::npos) << refused.status();
}

TEST_F(JobServiceTest, AnUploadIsDecodedOnceUnlessTheServerRestarted) {
  auto local = LocalDirBlobStore::Open((dir_ / "jobs").string());
  ASSERT_TRUE(local.ok());
  auto blobs = std::make_shared<CountingBlobStore>(*std::move(local));
  options_.blobs = blobs;
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls", {{"iterations", "1"}}), Input(Encode(testing::SphereCloud(3000))));
  ASSERT_TRUE(job.ok());
  ASSERT_EQ(WaitTerminal(job->id).state, JobState::kSucceeded);
  EXPECT_EQ(blobs->opened("input.drc"), 0);  // The run took the cloud decoded at submission.

  // A job queued when the server stopped runs from its stored upload.
  HoldIamlsJobs();
  JobService& held = Open();
  auto first = held.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(3000))));
  auto second = held.Submit(Spec("iamls", {{"iterations", "1"}}), Input(Encode(testing::SphereCloud(3000))));
  ASSERT_TRUE(first.ok() && second.ok());
  latch_.WaitStarted(1);
  held.Shutdown();
  EXPECT_EQ(blobs->opened("input.drc"), 1);  // The latch keeps no decoded input: its run read it.
  options_.kind_overrides.clear();
  Open();
  EXPECT_EQ(WaitTerminal(second->id).state, JobState::kSucceeded);
  EXPECT_EQ(WaitTerminal(first->id).state, JobState::kSucceeded);
  EXPECT_EQ(blobs->opened("input.drc"), 3);  // Both read their stored upload after the restart.
}

// `cloud` in parts of `per_part` points, coded losslessly and in order, so that the parts
// joined are the cloud.
Uploads InParts(const core::PointCloud& cloud, size_t per_part) {
  io::DracoOptions exact;
  exact.position_bits = 0;
  exact.speed = 10;
  Uploads uploads;
  for (size_t begin = 0, part = 0; begin < cloud.size(); begin += per_part, ++part) {
    const size_t end = std::min(cloud.size(), begin + per_part);
    core::PointCloud piece;
    piece.positions.assign(cloud.positions.begin() + begin, cloud.positions.begin() + end);
    if (cloud.has_normals()) piece.normals.assign(cloud.normals.begin() + begin, cloud.normals.begin() + end);
    auto bytes = io::EncodeDracoPointCloud(piece, exact);
    EXPECT_TRUE(bytes.ok());
    uploads[InputPartSlot(static_cast<int64_t>(part))] = bytes.ok() ? *bytes : std::string();
  }
  return uploads;
}

// A PU job over tile_points reads a cloud in parts one part at a time, and gets the mesh of the
// cloud whole, also when it runs from the stored parts after a restart.
TEST_F(JobServiceTest, ACloudInPartsIsStreamedAndGivesTheMeshOfTheCloudWhole) {
  const core::PointCloud cloud = testing::DrilledBlockCloud(12'000, 2.0, 0.6, 0.3, 0.3);
  const JobSpec spec = Spec("pu", {{"tile_points", "3000"}, {"support_cap", "16"}});
  JobService& s = Open();
  auto whole = s.Submit(spec, InParts(cloud, cloud.size()));
  auto parts = s.Submit(spec, InParts(cloud, 2500));
  ASSERT_TRUE(whole.ok() && parts.ok()) << whole.status() << parts.status();
  EXPECT_EQ(parts->input_points, 12'000);
  const JobRecord whole_done = WaitTerminal(whole->id), parts_done = WaitTerminal(parts->id);
  ASSERT_EQ(whole_done.state, JobState::kSucceeded) << whole_done.error;
  ASSERT_EQ(parts_done.state, JobState::kSucceeded) << parts_done.error;
  EXPECT_EQ(Statistic(parts_done, "input_streamed"), 1);
  EXPECT_GE(Statistic(parts_done, "tiles"), 4);
  // Streamed in, streamed out: the mesh comes as one part per tile, never whole.
  EXPECT_EQ(Statistic(parts_done, "mesh_parts"), Statistic(parts_done, "tiles"));
  auto expected = io::DecodeDracoMesh(ReadResult(whole->id, "mesh.drc"));
  ASSERT_TRUE(expected.ok());
  core::TriangleMesh streamed;
  for (const std::string& name : parts_done.results) {
    ASSERT_EQ(MeshPartOf(name), static_cast<int64_t>(&name - parts_done.results.data())) << name;
    auto part = io::DecodeMeshPart(ReadResult(parts->id, name));
    ASSERT_TRUE(part.ok()) << part.status();
    ASSERT_EQ(part->first_vertex, static_cast<int64_t>(streamed.vertices.size()));
    streamed.vertices.insert(streamed.vertices.end(), part->vertices.begin(), part->vertices.end());
    for (const auto& f : part->faces) {
      streamed.faces.push_back({static_cast<uint32_t>(f[0]), static_cast<uint32_t>(f[1]), static_cast<uint32_t>(f[2])});
    }
  }
  EXPECT_EQ(streamed.faces.size(), expected->faces.size());
  EXPECT_EQ(streamed.vertices.size(), expected->vertices.size());
  EXPECT_EQ(Statistic(parts_done, "triangles"), static_cast<double>(streamed.faces.size()));
  // Its closure is counted as the parts go, and agrees with the whole mesh's.
  EXPECT_EQ(Statistic(parts_done, "boundary_edges"), 0);
  EXPECT_EQ(Statistic(parts_done, "components"), 1);
  EXPECT_EQ(Statistic(whole_done, "components"), 1);
  const core::MeshTopology topology = core::AnalyzeTopology(core::WeldByPosition(streamed));
  EXPECT_TRUE(topology.watertight());
  EXPECT_EQ(topology.euler_characteristic(), 0);  // The block's one hole.
  EXPECT_NEAR(core::EnclosedVolume(streamed), core::EnclosedVolume(*expected), 1e-6 * core::EnclosedVolume(*expected));

  // Queued when the server stops, it runs from the parts as stored.
  options_.kind_overrides["pu"] = &latch_;
  JobService& held = Open();
  auto first = held.Submit(spec, InParts(cloud, 2500));
  auto second = held.Submit(spec, InParts(cloud, 2500));
  ASSERT_TRUE(first.ok() && second.ok());
  latch_.WaitStarted(1);
  held.Shutdown();
  options_.kind_overrides.clear();
  Open();
  for (const std::string& id : {first->id, second->id}) {
    const JobRecord done = WaitTerminal(id);
    ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
    EXPECT_EQ(Statistic(done, "input_streamed"), 1);
    EXPECT_EQ(Statistic(done, "triangles"), static_cast<double>(expected->faces.size()));
  }
}

// RGBA pixels of a PNG, decoded by stb_image; empty when it does not decode.
std::vector<uint8_t> DecodePng(const std::string& png, int& w, int& h) {
  int channels = 0;
  unsigned char* pixels = stbi_load_from_memory(reinterpret_cast<const stbi_uc*>(png.data()),
                                                static_cast<int>(png.size()), &w, &h, &channels, 4);
  if (pixels == nullptr) return {};
  std::vector<uint8_t> out(pixels, pixels + 4 * static_cast<size_t>(w) * static_cast<size_t>(h));
  stbi_image_free(pixels);
  return out;
}

// Pixels that are not the white background.
int64_t Covered(const std::vector<uint8_t>& rgba) {
  int64_t covered = 0;
  for (size_t i = 0; i + 3 < rgba.size(); i += 4) covered += rgba[i] < 250 || rgba[i + 1] < 250 || rgba[i + 2] < 250;
  return covered;
}

// A running job's mesh parts are listed and fetchable as soon as they are stored; nothing else
// of it is. A run cut short by a shutdown takes its parts back off the list.
TEST_F(JobServiceTest, MeshPartsCanBeFetchedWhileTheJobRuns) {
  const std::vector<core::Vec3f> triangle = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  const std::vector<std::array<int64_t, 3>> face = {{0, 1, 2}};
  const std::string part = io::EncodeMeshPart(0, triangle, {}, {}, face);
  latch_.WriteBeforeHolding(MeshPartArtifact(0), part);
  latch_.WriteBeforeHolding("scratch.txt", "not published early");
  options_.kind_overrides["pu"] = &latch_;
  JobService& s = Open();
  auto job = s.Submit(Spec("pu"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok()) << job.status();
  latch_.WaitStarted(1);
  const JobRecord running = WaitUntil(job->id, [](const JobRecord& r) { return !r.results.empty(); });
  EXPECT_EQ(running.state, JobState::kRunning);
  EXPECT_EQ(running.results, std::vector<std::string>{MeshPartArtifact(0)});
  EXPECT_EQ(ReadResult(job->id, MeshPartArtifact(0)), part);
  EXPECT_EQ(s.OpenResult(job->id, "scratch.txt").status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(s.OpenResult(job->id, "").status().code(), absl::StatusCode::kFailedPrecondition);
  if (LSQSURF_WITH_EGL) {
    // The picture of a running job: the surface done so far, the one part here.
    core::ParamSet view = DefaultView();
    ASSERT_TRUE(view.Parse("width", "64").ok() && view.Parse("height", "64").ok());
    auto picture = s.Render({}, job->id, "", view, nullptr);
    ASSERT_TRUE(picture.ok()) << picture.status();
    int w = 0, h = 0;
    EXPECT_GT(Covered(DecodePng(picture->png, w, h)), 64 * 64 / 16);  // The triangle, seen at 25° above its plane.
    EXPECT_EQ(s.Render({}, job->id, "scratch.txt", view, nullptr).status().code(),
              absl::StatusCode::kFailedPrecondition);
  }

  // Stopped while it runs: queued again without the parts it listed; the next run is the engine.
  s.Shutdown();
  options_.kind_overrides.clear();
  JobService& reopened = Open();
  const JobRecord done = WaitTerminal(job->id);
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_EQ(done.results.front(), "mesh.drc");
  EXPECT_EQ(std::count(done.results.begin(), done.results.end(), MeshPartArtifact(0)), 0);
  EXPECT_TRUE(reopened.OpenResult(job->id, "mesh.drc").ok());
}

// A mesh delivered in parts is drawn from its parts, one at a time, into the picture the whole
// mesh gives: its preview, and Render of its first result.
TEST_F(JobServiceTest, AMeshInPartsIsDrawnAsTheWholeMeshIs) {
  if (!LSQSURF_WITH_EGL) GTEST_SKIP() << "built without EGL: no pictures can be drawn";
  const core::PointCloud cloud = testing::DrilledBlockCloud(12'000, 2.0, 0.6, 0.3, 0.3);
  JobSpec spec = Spec("pu", {{"tile_points", "3000"}, {"support_cap", "16"}});
  spec.preview.enabled = true;
  spec.preview.view = DefaultView();
  for (const auto& [name, value] : {std::pair{"width", "160"}, {"height", "120"}, {"samples", "1"}}) {
    ASSERT_TRUE(spec.preview.view.Parse(name, value).ok()) << name;
  }
  JobService& s = Open();
  auto whole = s.Submit(spec, InParts(cloud, cloud.size()));
  auto parts = s.Submit(spec, InParts(cloud, 2500));
  ASSERT_TRUE(whole.ok() && parts.ok()) << whole.status() << parts.status();
  const JobRecord whole_done = WaitTerminal(whole->id), parts_done = WaitTerminal(parts->id);
  ASSERT_EQ(parts_done.state, JobState::kSucceeded) << parts_done.error;
  ASSERT_EQ(whole_done.state, JobState::kSucceeded) << whole_done.error;
  ASSERT_GE(Statistic(parts_done, "mesh_parts"), 4);
  EXPECT_EQ(std::count(parts_done.results.begin(), parts_done.results.end(), "preview.png"), 1);
  for (const auto& [name, value] : parts_done.statistics) EXPECT_NE(name, "preview_failures");
  // The parts' pictures against the whole mesh's: only silhouette pixels may differ (the whole,
  // closed mesh has its back faces culled; the open parts are drawn two-sided).
  std::vector<std::pair<std::string, std::string>> pairs = {
      {ReadResult(whole->id, "preview.png"), ReadResult(parts->id, "preview.png")}};
  auto view = spec.preview.view;
  ASSERT_TRUE(view.SetText("color", "depth").ok());
  auto whole_picture = s.Render({}, whole->id, "mesh.drc", view, nullptr);
  auto parts_picture = s.Render({}, parts->id, "", view, nullptr);
  ASSERT_TRUE(whole_picture.ok() && parts_picture.ok()) << whole_picture.status() << parts_picture.status();
  EXPECT_EQ(s.Render({}, parts->id, MeshPartArtifact(99999), view, nullptr).status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(parts_picture->color_min, whole_picture->color_min);
  EXPECT_EQ(parts_picture->color_max, whole_picture->color_max);
  pairs.emplace_back(whole_picture->png, parts_picture->png);
  for (const auto& [a, b] : pairs) {
    int wa = 0, ha = 0, wb = 0, hb = 0;
    const auto pa = DecodePng(a, wa, ha), pb = DecodePng(b, wb, hb);
    ASSERT_EQ(wa, 160);
    ASSERT_EQ(ha, 120);
    ASSERT_EQ(pa.size(), pb.size());
    int64_t differing = 0;
    for (size_t i = 0; i < pa.size(); i += 4) differing += !std::equal(&pa[i], &pa[i] + 3, &pb[i]);
    EXPECT_GT(Covered(pa), 160 * 120 / 10);
    EXPECT_LT(differing, Covered(pa) / 20) << "of " << Covered(pa);
  }
}

// A tiled run keeps its point files in the server's data directory, and a start removes what a
// crashed run left there.
TEST_F(JobServiceTest, TheScratchOfACrashedRunIsRemovedAtStart) {
  const std::filesystem::path scratch = dir_ / "scratch";
  const pid_t child = fork();
  if (child == 0) _exit(0);
  int status = 0;
  waitpid(child, &status, 0);  // Its id now names no process, as a crashed server's.
  const std::filesystem::path left = scratch / ("lsqsurf-tiles-" + std::to_string(child) + "-Xy12Zw");
  std::filesystem::create_directories(left);
  std::ofstream(left / "tile-1.pts") << "points of a run that crashed";
  JobService& s = Open();
  EXPECT_FALSE(std::filesystem::exists(left));
  auto job = s.Submit(Spec("pu", {{"tile_points", "1000"}}), Input(Encode(testing::SphereCloud(3000))));
  ASSERT_TRUE(job.ok()) << job.status();
  const JobRecord done = WaitTerminal(job->id);
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_GT(Statistic(done, "tile_scratch_bytes"), 0);
  EXPECT_TRUE(std::filesystem::is_empty(scratch));  // The run's own files went with it.
}

// Other methods, and clouds without normals, join the parts; parts that do not fit are refused.
TEST_F(JobServiceTest, PartsAreJoinedWhereTheyCannotStreamAndMustAgree) {
  JobService& s = Open();
  const core::PointCloud sphere = testing::SphereCloud(3000);
  auto whole = s.Submit(Spec("iamls"), InParts(sphere, sphere.size()));
  auto parts = s.Submit(Spec("iamls"), InParts(sphere, 1000));
  core::PointCloud bare = sphere;
  bare.normals.clear();
  auto unoriented = s.Submit(Spec("pu", {{"tile_points", "1000"}}), InParts(bare, 1000));
  ASSERT_TRUE(whole.ok() && parts.ok() && unoriented.ok());
  const JobRecord whole_done = WaitTerminal(whole->id), parts_done = WaitTerminal(parts->id);
  ASSERT_EQ(parts_done.state, JobState::kSucceeded) << parts_done.error;
  EXPECT_EQ(Statistic(parts_done, "triangles"), Statistic(whole_done, "triangles"));
  const JobRecord unoriented_done = WaitTerminal(unoriented->id);
  ASSERT_EQ(unoriented_done.state, JobState::kSucceeded) << unoriented_done.error;
  EXPECT_GT(Statistic(unoriented_done, "normals_seconds"), 0);  // Joined, so its normals could be estimated.

  Uploads mixed = InParts(sphere, 1000);
  mixed[InputPartSlot(1)] = InParts(bare, 1000)[InputPartSlot(1)];
  const absl::Status mixed_status = s.Submit(Spec("pu"), mixed).status();
  EXPECT_EQ(mixed_status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(mixed_status.message().find("input part 1 lacks normals"), std::string::npos) << mixed_status;
  Uploads gap = InParts(sphere, 1000);
  gap.erase(InputPartSlot(1));
  const absl::Status gap_status = s.Submit(Spec("pu"), gap).status();
  EXPECT_NE(gap_status.message().find("without a gap"), std::string::npos) << gap_status;
  Uploads too_many = InParts(sphere, 1000);
  options_.max_points = 2500;
  JobService& small = Open();
  const absl::Status over = small.Submit(Spec("pu"), too_many).status();
  EXPECT_EQ(over.code(), absl::StatusCode::kResourceExhausted) << over;
  const absl::Status volume = small.Submit(Spec("volume", {{"field", "p"}}), InParts(sphere, 1000)).status();
  EXPECT_NE(volume.message().find("takes no 'input.1' upload"), std::string::npos) << volume;
}

TEST_F(JobServiceTest, JobsSurviveARestart) {
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls", {{"iterations", "2"}}), Input(Encode(testing::SphereCloud(3000))));
  ASSERT_TRUE(job.ok());
  const std::string id = job->id;
  ASSERT_EQ(WaitTerminal(id).state, JobState::kSucceeded);
  const std::string mesh = ReadResult(id, "mesh.drc");
  JobService& reopened = Open();
  auto again = reopened.Get(id);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->state, JobState::kSucceeded);
  EXPECT_EQ(again->spec.params.Get("iterations"), 2);
  EXPECT_EQ(again->spec.params.Get("epsilon"), Spec("iamls").params.Get("epsilon"));  // Unset: the default.
  EXPECT_FALSE(again->statistics.empty());
  EXPECT_EQ(ReadResult(id, "mesh.drc"), mesh);
}

TEST_F(JobServiceTest, PreviewsAreCheckedDrawnAndSurviveARestart) {
  if (!LSQSURF_WITH_EGL) GTEST_SKIP() << "built without EGL: no previews can be drawn";
  JobService& s = Open();
  const Uploads input = Input(Encode(testing::SphereCloud(3000)));
  JobSpec spec = Spec("iamls", {{"iterations", "2"}});
  spec.preview.enabled = true;
  spec.preview.view = DefaultView();
  ASSERT_TRUE(spec.preview.view.SetText("color", "degree").ok());  // Only PU meshes carry it.
  auto refused = s.Submit(spec, input);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("no attribute 'degree'"), std::string_view::npos) << refused.status();
  ASSERT_TRUE(spec.preview.view.SetText("color", "").ok());

  ASSERT_TRUE(spec.preview.view.Parse("width", "96").ok());
  ASSERT_TRUE(spec.preview.view.Parse("height", "64").ok());
  ASSERT_TRUE(spec.preview.view.Parse("up_axis", "y").ok());
  ASSERT_TRUE(spec.preview.view.Parse("azimuth_deg", "10").ok());
  ASSERT_TRUE(spec.preview.view.Parse("wireframe", "true").ok());
  auto job = s.Submit(spec, input);
  ASSERT_TRUE(job.ok()) << job.status();
  const JobRecord done = WaitTerminal(job->id);
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_NE(std::find(done.results.begin(), done.results.end(), "preview.png"), done.results.end());
  const std::string png = ReadResult(job->id, "preview.png");
  // PNG signature, then the IHDR chunk: big-endian width and height at bytes 16 and 20.
  ASSERT_GT(png.size(), 24u);
  EXPECT_EQ(png.substr(0, 8), std::string("\x89PNG\r\n\x1a\n", 8));
  auto be32 = [&](size_t at) {
    uint32_t v = 0;
    for (size_t i = 0; i < 4; ++i) v = v << 8 | static_cast<uint8_t>(png[at + i]);
    return v;
  };
  EXPECT_EQ(be32(16), 96u);
  EXPECT_EQ(be32(20), 64u);

  JobService& reopened = Open();
  auto again = reopened.Get(job->id);
  ASSERT_TRUE(again.ok());
  const PreviewSpec& kept = again->spec.preview;
  EXPECT_TRUE(kept.enabled);
  EXPECT_EQ(kept.view.Encode(), spec.preview.view.Encode());
}

TEST_F(JobServiceTest, DatabasesFromEarlierVersionsStillOpen) {
  // The table as the first releases wrote it, with one finished job, and a later one with a
  // preview in the old text form.
  {
    sqlite3* db = nullptr;
    std::filesystem::create_directories(dir_);
    ASSERT_EQ(sqlite3_open((dir_ / "jobs.db").string().c_str(), &db), SQLITE_OK);
    const char* sql =
        "CREATE TABLE jobs (id TEXT PRIMARY KEY, method TEXT, parameters TEXT, mesh_bits INTEGER, state INTEGER, "
        "stage TEXT, attempts INTEGER, error TEXT, created_ms INTEGER, updated_ms INTEGER, input_points INTEGER, "
        "input_bytes INTEGER, statistics TEXT, results TEXT);"
        "INSERT INTO jobs VALUES ('cccc', 'iamls', 'iterations=3;', 16, 2, 'done', 1, '', 1, 2, 3000, 100, "
        "'wall_seconds=1;', 'mesh.drc;');"
        "INSERT INTO jobs VALUES ('dddd', 'track', 'interface=2;field=1;resampling=0;steps=20;', 16, 2, 'done', 1, "
        "'', 1, 2, 0, 0, '', 'stats.csv;');";
    EXPECT_EQ(sqlite3_exec(db, sql, nullptr, nullptr, nullptr), SQLITE_OK);
    sqlite3_close(db);
  }
  JobService& s = Open();
  auto old = s.Get("cccc");
  ASSERT_TRUE(old.ok()) << old.status();
  EXPECT_EQ(old->state, JobState::kSucceeded);
  EXPECT_EQ(old->spec.params.Get("iterations"), 3);
  EXPECT_FALSE(old->spec.preview.enabled);
  EXPECT_EQ(old->owner, "");
  EXPECT_EQ(old->stored_bytes, 100);  // Its upload, as recorded then.
  auto track = s.Get("dddd");
  ASSERT_TRUE(track.ok()) << track.status();
  // Numeric codes of the time before enums map to the same choices.
  EXPECT_EQ(track->spec.params.Get("interface"), static_cast<int>(TrackInterface::kZalesak));
  EXPECT_EQ(track->spec.params.Get("field"), static_cast<int>(TrackField::kDeformation));
  EXPECT_EQ(track->spec.params.Get("steps"), 20);
}

TEST_F(JobServiceTest, QueuedJobsWhoseSpecNoLongerFitsFailWithTheReason) {
  {
    auto store = SqliteJobStore::Open((std::filesystem::create_directories(dir_), dir_ / "jobs.db").string(),
                                      RegistrySpecTables());
    ASSERT_TRUE(store.ok());
    JobRecord stale;
    stale.id = "eeee";
    stale.spec = Spec("iamls");
    stale.spec.params.Mutable<IamlsJobParams>()->fit.epsilon = 9;  // As if the range had shrunk since.
    stale.state = JobState::kQueued;
    ASSERT_TRUE((*store)->Insert(stale).ok());
  }
  JobService& s = Open();
  const JobRecord r = *s.Get("eeee");
  EXPECT_EQ(r.state, JobState::kFailed);
  EXPECT_NE(r.error.find("epsilon=9"), std::string::npos) << r.error;
}

TEST_F(JobServiceTest, CrashedJobsRunAgainOnceThenFail) {
  // The records a killed server leaves behind: jobs marked running.
  std::filesystem::create_directories(dir_ / "jobs" / "aaaa");
  std::filesystem::create_directories(dir_ / "jobs" / "bbbb");
  const std::string input = Encode(testing::SphereCloud(3000));
  ASSERT_TRUE(io::WriteFileAtomically((dir_ / "jobs" / "aaaa" / "input.drc").string(), input).ok());
  ASSERT_TRUE(io::WriteFileAtomically((dir_ / "jobs" / "bbbb" / "input.drc").string(), input).ok());
  {
    auto store = SqliteJobStore::Open((dir_ / "jobs.db").string(), RegistrySpecTables());
    ASSERT_TRUE(store.ok());
    JobRecord once;
    once.id = "aaaa";
    once.spec = Spec("iamls");
    once.state = JobState::kRunning;
    once.attempts = 1;
    JobRecord twice = once;
    twice.id = "bbbb";
    twice.attempts = 2;
    ASSERT_TRUE((*store)->Insert(once).ok());
    ASSERT_TRUE((*store)->Insert(twice).ok());
  }
  JobService& s = Open();
  EXPECT_EQ(s.Get("bbbb")->state, JobState::kFailed);
  EXPECT_NE(s.Get("bbbb")->error.find("giving up"), std::string::npos);
  const JobRecord resumed = WaitTerminal("aaaa");
  EXPECT_EQ(resumed.state, JobState::kSucceeded) << resumed.error;
  EXPECT_EQ(resumed.attempts, 2);
}

TEST_F(JobServiceTest, ShutdownRequeuesTheRunningJobWithoutHoldingItAgainstIt) {
  options_.max_attempts = 1;  // A crash would fail it; a graceful stop must not.
  HoldIamlsJobs();
  JobService& s = Open();
  auto job = s.Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(3000))));
  ASSERT_TRUE(job.ok());
  latch_.WaitStarted(1);
  s.Shutdown();
  const JobRecord stopped = *s.Get(job->id);
  EXPECT_EQ(stopped.state, JobState::kQueued);
  EXPECT_EQ(stopped.attempts, 1);
  EXPECT_EQ(stopped.interruptions, 1);
  EXPECT_EQ(s.Submit(Spec("iamls"), Input("x")).status().code(), absl::StatusCode::kUnavailable);
  options_.kind_overrides.clear();  // The real engine this time.
  Open();
  const JobRecord done = WaitTerminal(job->id);
  EXPECT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_EQ(done.attempts, 2);
}

#if LSQSURF_WITH_POSTGRESQL  // Servers sharing a store need PostgreSQL.
// A store that passes every call to another; the stores below change a few of them.
class ForwardingStore : public JobStore {
 public:
  explicit ForwardingStore(std::shared_ptr<JobStore> inner) : inner_(std::move(inner)) {}
  bool shared() const override { return inner_->shared(); }
  absl::Status Insert(const JobRecord& r) override { return inner_->Insert(r); }
  absl::StatusOr<std::optional<JobRecord>> Claim(const std::string& runner, std::chrono::milliseconds lease,
                                                 const ClaimScope& scope) override {
    return inner_->Claim(runner, lease, scope);
  }
  absl::StatusOr<int64_t> WriteHeld(const JobRecord& r) override { return inner_->WriteHeld(r); }
  absl::StatusOr<std::vector<std::pair<std::string, bool>>> Renew(const std::string& runner,
                                                                  const std::vector<std::string>& ids,
                                                                  std::chrono::milliseconds lease) override {
    return inner_->Renew(runner, ids, lease);
  }
  absl::StatusOr<std::vector<JobRecord>> RecoverLapsed(bool every_running,
                                                       const std::function<void(JobRecord&)>& recover) override {
    return inner_->RecoverLapsed(every_running, recover);
  }
  absl::StatusOr<JobRecord> Cancel(const std::string& id, const std::string& reason) override {
    return inner_->Cancel(id, reason);
  }
  absl::Status Remove(const std::string& id) override { return inner_->Remove(id); }
  absl::StatusOr<JobRecord> Get(const std::string& id) override { return inner_->Get(id); }
  absl::StatusOr<JobChanges> ChangesSince(int64_t seq) override { return inner_->ChangesSince(seq); }
  void WaitForOthers(std::chrono::milliseconds timeout) override { inner_->WaitForOthers(timeout); }
  absl::StatusOr<std::string> Agree(const std::string& key, const std::string& value) override {
    return inner_->Agree(key, value);
  }

 protected:
  std::shared_ptr<JobStore> inner_;
};

// A store that lets its server claim one job and then neither renew its lease nor claim
// another, as for a server cut off from the database after it took a job; with `unreachable`
// its server's looks for changes fail as well.
class CutOffStore final : public ForwardingStore {
 public:
  using ForwardingStore::ForwardingStore;
  absl::StatusOr<std::optional<JobRecord>> Claim(const std::string& runner, std::chrono::milliseconds lease,
                                                 const ClaimScope& scope) override {
    if (claimed_) return absl::UnavailableError("claims are cut off");
    auto claimed = inner_->Claim(runner, lease, scope);
    if (claimed.ok() && claimed->has_value()) claimed_ = true;
    return claimed;
  }
  absl::StatusOr<std::vector<std::pair<std::string, bool>>> Renew(const std::string&, const std::vector<std::string>&,
                                                                  std::chrono::milliseconds) override {
    return absl::UnavailableError("renewals are cut off");
  }
  absl::StatusOr<JobChanges> ChangesSince(int64_t seq) override {
    if (unreachable) return absl::UnavailableError("the store does not answer");
    return inner_->ChangesSince(seq);
  }

  std::atomic<bool> unreachable{false};  // Its server's looks at the store fail too.

 private:
  std::atomic<bool> claimed_{false};
};

// A store whose server's final write of a job is stored at once but answered only when the
// test opens the gate, so that the test can act in between (as another server may); it also
// counts its server's looks for changes.
class FinalWriteGate final : public ForwardingStore {
 public:
  using ForwardingStore::ForwardingStore;
  absl::StatusOr<int64_t> WriteHeld(const JobRecord& r) override {
    auto seq = inner_->WriteHeld(r);
    if (!IsTerminal(r.state)) return seq;
    std::unique_lock lock(mutex_);
    written_ = true;
    changed_.notify_all();
    changed_.wait(lock, [&] { return open_; });
    return seq;
  }
  absl::StatusOr<JobChanges> ChangesSince(int64_t seq) override {
    auto changes = inner_->ChangesSince(seq);
    std::lock_guard lock(mutex_);
    ++looks_;
    changed_.notify_all();
    return changes;
  }
  void WaitWritten() {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return written_; });
  }
  // Blocks until the server has finished two looks begun after this call (so one whole look
  // saw everything stored before it).
  void WaitTwoLooks() {
    std::unique_lock lock(mutex_);
    const int64_t target = looks_ + 2;
    changed_.wait(lock, [&] { return looks_ >= target; });
  }
  void Open() {
    std::lock_guard lock(mutex_);
    open_ = true;
    changed_.notify_all();
  }

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  bool written_ = false, open_ = false;
  int64_t looks_ = 0;
};

// Two services on one PostgreSQL database (a throwaway server this test process starts), as
// two servers behind a balancer: each with its own connections, folder and runner name.
class SharedJobServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string why_not;
    testing::PostgresCluster* cluster = testing::SharedPostgresCluster(&why_not);
    if (cluster == nullptr) GTEST_SKIP() << why_not;
    url_ = cluster->NewDatabase();
    ASSERT_FALSE(url_.empty());
    dir_ = testing::FreshTestDir("lsqsurf-shared");
  }
  void TearDown() override {
    for (testing::LatchKind* latch : {&latch_a_, &latch_b_}) latch->Release();
    a_.reset();
    b_.reset();
    std::filesystem::remove_all(dir_);
  }
  // A service on the shared database; `wrap` may stand between it and the store.
  std::unique_ptr<JobService> OpenService(
      const std::string& name, testing::LatchKind* latch, std::chrono::milliseconds lease,
      const std::function<std::shared_ptr<JobStore>(std::shared_ptr<JobStore>)>& wrap = nullptr) {
    auto service = TryOpenService(name, latch, lease, wrap);
    EXPECT_TRUE(service.ok()) << service.status();
    return service.ok() ? *std::move(service) : nullptr;
  }
  // The same, with the bytes in `blobs` rather than in the database, and the error kept.
  absl::StatusOr<std::unique_ptr<JobService>> TryOpenService(
      const std::string& name, testing::LatchKind* latch, std::chrono::milliseconds lease,
      const std::function<std::shared_ptr<JobStore>(std::shared_ptr<JobStore>)>& wrap = nullptr,
      std::shared_ptr<BlobStore> blobs = nullptr) {
    auto store = PostgresJobStore::Open(url_, RegistrySpecTables());
    if (!store.ok()) return store.status();
    JobServiceOptions options;
    options.data_dir = (dir_ / name).string();
    options.name = name;
    options.lease = lease;
    options.blobs = blobs != nullptr ? blobs : std::make_shared<PostgresBlobStore>((*store)->pool());
    options.store = *std::move(store);
    if (wrap) options.store = wrap(options.store);
    if (latch != nullptr) options.kind_overrides["iamls"] = latch;
    return JobService::Open(options);
  }
  static JobRecord WaitUntil(JobService& s, const std::string& id,
                             const std::function<bool(const absl::StatusOr<JobRecord>&)>& done) {
    // The deadline only turns a defect that would hang into a failure; it times nothing.
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::minutes(2);
    absl::StatusOr<JobRecord> r = s.Get(id);
    while (!done(r) && std::chrono::steady_clock::now() < give_up) {
      if (!r.ok()) return {};
      r = s.WaitForChange(id, r->version, std::chrono::seconds(1));
    }
    return r.ok() ? *r : JobRecord{};
  }

  std::string url_;
  std::filesystem::path dir_;
  testing::LatchKind latch_a_, latch_b_;
  std::unique_ptr<JobService> a_, b_;
};

// A server whose --blob-dir is a folder of its own would take jobs whose uploads it cannot read:
// it is refused at start, saying why, while servers on the one shared folder start and run.
TEST_F(SharedJobServiceTest, AServerWhoseBlobStoreIsNotTheSharedOneDoesNotStart) {
  const auto folder = [&](const std::string& name) -> std::shared_ptr<BlobStore> {
    auto blobs = LocalDirBlobStore::Open((dir_ / name).string());
    EXPECT_TRUE(blobs.ok()) << blobs.status();
    return blobs.ok() ? std::shared_ptr<BlobStore>(*std::move(blobs)) : nullptr;
  };
  auto a = TryOpenService("a", nullptr, std::chrono::seconds(10), nullptr, folder("shared-blobs"));
  ASSERT_TRUE(a.ok()) << a.status();
  a_ = *std::move(a);
  auto b = TryOpenService("b", nullptr, std::chrono::seconds(10), nullptr, folder("shared-blobs"));
  ASSERT_TRUE(b.ok()) << b.status();
  b_ = *std::move(b);
  auto apart = TryOpenService("c", nullptr, std::chrono::seconds(10), nullptr, folder("c-own-blobs"));
  EXPECT_EQ(apart.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(apart.status().message(), "--blob-dir")) << apart.status();
  // The refused server left nothing in the shared folder, nor anything behind in its own.
  const auto blobs_in = [&](const std::string& name) {
    int count = 0;
    for (const auto& entry : std::filesystem::recursive_directory_iterator(dir_ / name)) {
      count += entry.is_regular_file();
    }
    return count;
  };
  EXPECT_EQ(blobs_in("shared-blobs"), 1);  // A's witness; B's own went once it had read A's.
  EXPECT_EQ(blobs_in("c-own-blobs"), 0);

  // B runs a job A accepted (A stops at once, handing it back if it took it): its upload is read
  // from the folder they share.
  auto job = a_->Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok()) << job.status();
  a_.reset();
  const JobRecord done = WaitUntil(*b_, job->id, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  EXPECT_EQ(done.state, JobState::kSucceeded) << done.error;
}

// An idle worker takes the tiles of a running tiled build before a new job: the build that has
// begun finishes first. B's one worker finds a queued job (held on a latch once it runs) and
// A's tiled build; it makes tiles of the build until none is left, and only then the job.
TEST_F(SharedJobServiceTest, AnIdleWorkerTakesTheTilesOfARunningBuildBeforeANewJob) {
  a_ = OpenService("a", nullptr, std::chrono::seconds(10));
  ASSERT_NE(a_, nullptr);
  auto build = a_->Submit(Spec("pu", {{"tile_points", "1000"}, {"support_cap", "16"}}),
                          Input(Encode(testing::SphereCloud(8'000))));
  ASSERT_TRUE(build.ok()) << build.status();
  // A's one worker runs the build; once its tiles are queued (one is made), a job waits behind it.
  auto store = PostgresJobStore::Open(url_, RegistrySpecTables());
  ASSERT_TRUE(store.ok()) << store.status();
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::minutes(2);
  for (;;) {
    auto all = (*store)->ChangesSince(0);
    ASSERT_TRUE(all.ok()) << all.status();
    if (std::any_of(all->changed.begin(), all->changed.end(),
                    [&](const JobRecord& r) { return r.parent == build->id && r.state == JobState::kSucceeded; }))
      break;
    ASSERT_FALSE(IsTerminal(a_->Get(build->id)->state)) << "the build ended untiled";
    ASSERT_LT(std::chrono::steady_clock::now(), give_up) << "the build made no tile";
    (*store)->WaitForOthers(std::chrono::milliseconds(100));
  }
  auto waiting = a_->Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(waiting.ok()) << waiting.status();
  b_ = OpenService("b", &latch_b_, std::chrono::seconds(10));
  ASSERT_NE(b_, nullptr);
  const JobRecord built = WaitUntil(*a_, build->id, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  ASSERT_EQ(built.state, JobState::kSucceeded) << built.error;
  ASSERT_GE(Statistic(built, "tiles"), 4) << "too few tiles to share";
  EXPECT_EQ(Statistic(built, "replicas"), 2) << "B took the new job before the build's tiles";
  latch_b_.WaitStarted(1);  // Then B runs the job.
  EXPECT_EQ(b_->Get(waiting->id)->runner.substr(0, 2), "b/");
  latch_b_.Release();
  const JobRecord ran = WaitUntil(*b_, waiting->id, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  EXPECT_EQ(ran.state, JobState::kSucceeded) << ran.error;
}

TEST_F(SharedJobServiceTest, TwoServicesShareOneQueueAndAnswerForEachOthersJobs) {
  a_ = OpenService("a", &latch_a_, std::chrono::seconds(10));
  b_ = OpenService("b", &latch_b_, std::chrono::seconds(10));
  ASSERT_TRUE(a_ && b_);
  const Uploads input = Input(Encode(testing::SphereCloud(1000)));
  auto first = a_->Submit(Spec("iamls"), input);
  auto second = a_->Submit(Spec("iamls"), input);
  ASSERT_TRUE(first.ok() && second.ok());
  // One worker each: each service takes one of the two jobs.
  latch_a_.WaitStarted(1);
  latch_b_.WaitStarted(1);
  const JobRecord one = WaitUntil(*b_, first->id, [](const auto& r) { return r.ok() && !r->runner.empty(); });
  const JobRecord two = WaitUntil(*b_, second->id, [](const auto& r) { return r.ok() && !r->runner.empty(); });
  EXPECT_EQ(one.state, JobState::kRunning);
  EXPECT_EQ(two.state, JobState::kRunning);
  ASSERT_EQ(std::set<std::string>({one.runner, two.runner}), std::set<std::string>({a_->runner(), b_->runner()}));
  const std::string on_a = one.runner == a_->runner() ? one.id : two.id;
  const std::string on_b = one.runner == a_->runner() ? two.id : one.id;

  // A cancellation asked of B reaches A, which runs the job.
  auto requested = b_->Cancel(on_a);
  ASSERT_TRUE(requested.ok()) << requested.status();
  EXPECT_EQ(requested->state, JobState::kRunning);
  const JobRecord cancelled = WaitUntil(*b_, on_a, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  EXPECT_EQ(cancelled.state, JobState::kCancelled);

  // B's job succeeds; A serves its result, then deletes it, and B hears of the deletion.
  latch_b_.Release();
  const JobRecord done = WaitUntil(*a_, on_b, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  auto reader = a_->OpenResult(on_b, "held.txt");
  ASSERT_TRUE(reader.ok()) << reader.status();
  EXPECT_EQ(ReadAll(**reader).value(), "released");
  ASSERT_TRUE(a_->retention().Delete(on_b).ok());
  WaitUntil(*b_, on_b, [](const auto& r) { return !r.ok(); });
  EXPECT_EQ(b_->Get(on_b).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(b_->List().size(), 1u);
}

TEST_F(SharedJobServiceTest, AJobDeletedElsewhereAsItsRunEndsLeavesNothingBehind) {
  // B's final write reaches the store, and before B hears back A sees the outcome and deletes
  // the job; B looks for changes meanwhile and sees both its own write and the deletion.
  std::shared_ptr<FinalWriteGate> gate;
  b_ = OpenService("b", &latch_b_, std::chrono::seconds(10), [&gate](std::shared_ptr<JobStore> inner) {
    gate = std::make_shared<FinalWriteGate>(inner);
    return gate;
  });
  ASSERT_TRUE(b_ && gate);
  absl::Cleanup open_gate = [&gate] { gate->Open(); };
  auto job = b_->Submit(Spec("iamls"), Input(Encode(testing::SphereCloud(1000))));
  ASSERT_TRUE(job.ok()) << job.status();
  latch_b_.WaitStarted(1);
  a_ = OpenService("a", &latch_a_, std::chrono::seconds(10));
  ASSERT_TRUE(a_);
  latch_b_.Release();
  gate->WaitWritten();
  const JobRecord done = WaitUntil(*a_, job->id, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  ASSERT_TRUE(a_->retention().Delete(job->id).ok());
  gate->WaitTwoLooks();
  gate->Open();
  // B's run ends; the job is gone from B as from the store, and B says so to its watchers.
  const JobRecord last = WaitUntil(*b_, job->id, [](const auto& r) { return !r.ok(); });
  EXPECT_EQ(b_->Get(job->id).status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(b_->List().empty());
  EXPECT_EQ(a_->Get(job->id).status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(last.id.empty());
}

TEST_F(SharedJobServiceTest, AJobWhoseServerStopsRenewingItsLeaseRunsOnAnother) {
  // A holds its job on a latch it never releases, and can neither renew its 300 ms lease nor
  // claim the job again.
  a_ = OpenService("a", &latch_a_, std::chrono::milliseconds(300),
                   [](std::shared_ptr<JobStore> inner) { return std::make_shared<CutOffStore>(inner); });
  ASSERT_TRUE(a_);
  auto job = a_->Submit(Spec("iamls", {{"iterations", "1"}}), Input(Encode(testing::SphereCloud(3000))));
  ASSERT_TRUE(job.ok());
  latch_a_.WaitStarted(1);
  // B, with the real engine, finds the lapsed lease, queues the job again and runs it.
  b_ = OpenService("b", nullptr, std::chrono::seconds(1));
  ASSERT_TRUE(b_);
  const JobRecord done = WaitUntil(*b_, job->id, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  EXPECT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_EQ(done.attempts, 2);
  EXPECT_EQ(done.runner, b_->runner());
  // A learns that it lost the job: its run stops, and it shows B's outcome.
  const JobRecord seen_by_a = WaitUntil(*a_, job->id, [](const auto& r) { return r.ok() && IsTerminal(r->state); });
  EXPECT_EQ(seen_by_a.state, JobState::kSucceeded);
  EXPECT_EQ(seen_by_a.runner, b_->runner());
  auto mesh = io::DecodeDracoMesh(b_->OpenResult(job->id, "mesh.drc").value()->Next(size_t{1} << 30).value());
  EXPECT_TRUE(mesh.ok()) << mesh.status();
}

TEST_F(SharedJobServiceTest, AServiceSaysWhenItsStoreStopsAnswering) {
  std::shared_ptr<CutOffStore> faulty;
  a_ = OpenService("a", nullptr, std::chrono::seconds(10), [&](std::shared_ptr<JobStore> inner) {
    faulty = std::make_shared<CutOffStore>(inner);
    return faulty;
  });
  ASSERT_TRUE(a_ && faulty);
  EXPECT_TRUE(a_->StoreReachable());
  // The service looks at the store every poll (0.5 s); each wait is bounded at 20 s.
  const auto wait_for = [&](bool reachable) {
    for (int i = 0; i < 400 && a_->StoreReachable() != reachable; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return a_->StoreReachable() == reachable;
  };
  faulty->unreachable = true;
  EXPECT_TRUE(wait_for(false));
  faulty->unreachable = false;
  EXPECT_TRUE(wait_for(true));
}

#endif  // LSQSURF_WITH_POSTGRESQL

}  // namespace
}  // namespace lsqsurf::jobs
