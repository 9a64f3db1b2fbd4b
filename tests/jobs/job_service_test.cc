#include "worker/jobs/job_service.h"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <cmath>
#include <filesystem>
#include <limits>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/jobs/engines.h"
#include "worker/jobs/front_job.h"

namespace lsqsurf::jobs {
namespace {

std::string Encode(const core::PointCloud& cloud, int position_bits = 16) {
  io::DracoOptions options;
  options.position_bits = position_bits;
  auto bytes = io::EncodeDracoPointCloud(cloud, options);
  EXPECT_TRUE(bytes.ok());
  return bytes.ok() ? *bytes : std::string();
}

class JobServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("lsqsurf-jobs-" + std::to_string(::getpid()) + "-" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    std::filesystem::remove_all(dir_);
    options_.data_dir = dir_.string();
  }
  void TearDown() override {
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
  // Waits (at most ~5 min, for sanitizer builds) until the job satisfies `done`.
  JobRecord WaitUntil(const std::string& id, const std::function<bool(const JobRecord&)>& done) {
    auto r = service_->Get(id);
    for (int i = 0; i < 3000 && r.ok() && !done(*r); ++i) {
      r = service_->WaitForChange(id, r->version, std::chrono::milliseconds(100));
    }
    EXPECT_TRUE(r.ok());
    return r.ok() ? *r : JobRecord{};
  }
  JobRecord WaitTerminal(const std::string& id) {
    return WaitUntil(id, [](const JobRecord& r) { return IsTerminal(r.state); });
  }

  std::filesystem::path dir_;
  JobServiceOptions options_;
  std::unique_ptr<JobService> service_;
};

TEST_F(JobServiceTest, EveryMethodReconstructsASphere) {
  JobService& s = Open();
  for (const MethodSpec& method : SurfaceMethods()) {
    if (method.name == kTrackMethod) continue;  // Not a surface method (see the end-to-end test).
    auto job = s.Submit({method.name, {}}, Encode(testing::SphereCloud(5000)));
    ASSERT_TRUE(job.ok()) << job.status();
    EXPECT_EQ(job->state, JobState::kQueued);
    const JobRecord done = WaitTerminal(job->id);
    ASSERT_EQ(done.state, JobState::kSucceeded) << method.name << ": " << done.error;
    auto path = s.ResultPath(job->id, "mesh.drc");
    ASSERT_TRUE(path.ok());
    auto mesh = io::ReadMeshFile(*path);
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    const core::MeshTopology t = core::AnalyzeTopology(*mesh);
    EXPECT_TRUE(t.watertight()) << method.name;
    EXPECT_EQ(t.euler_characteristic(), 2) << method.name;
    EXPECT_NEAR(core::EnclosedVolume(*mesh) / (4.0 / 3.0 * M_PI), 1.0, 0.02) << method.name;
    EXPECT_FALSE(done.statistics.empty());
  }
}

TEST_F(JobServiceTest, EstimatesMissingNormalsByDefault) {
  JobService& s = Open();
  core::PointCloud cloud = testing::SphereCloud(4000);
  cloud.normals.clear();
  auto job = s.Submit({"iamls", {}}, Encode(cloud));
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
  struct Case {
    const char* what;
    JobSpec spec;
    std::string input;
    absl::StatusCode code;
    const char* fragment;
    std::string velocity = {};
  } cases[] = {
      {"empty upload", {"iamls", {}}, "", absl::StatusCode::kInvalidArgument, "no input"},
      {"truncated Draco", {"iamls", {}}, good.substr(0, good.size() / 2), absl::StatusCode::kInvalidArgument, "Draco"},
      {"not Draco", {"iamls", {}}, "hello", absl::StatusCode::kInvalidArgument, "Draco"},
      {"NaN", {"iamls", {}}, Encode(nan_cloud, /*lossless*/ 0), absl::StatusCode::kInvalidArgument, "NaN"},
      {"unknown method", {"poisson", {}}, good, absl::StatusCode::kInvalidArgument, "available: iamls"},
      {"unknown parameter", {"iamls", {{"epsilonn", 1}}}, good, absl::StatusCode::kInvalidArgument, "valid parameters"},
      {"out of range", {"iamls", {{"epsilon", 9}}}, good, absl::StatusCode::kInvalidArgument, "out of range"},
      {"not whole", {"iamls", {{"iterations", 2.5}}}, good, absl::StatusCode::kInvalidArgument, "whole number"},
      {"no normals, no estimation", {"iamls", {{"estimate_normals", 0}}}, Encode(no_normals),
       absl::StatusCode::kInvalidArgument, "no normals"},
      {"too many points", {"iamls", {}}, Encode(testing::SphereCloud(6000)), absl::StatusCode::kResourceExhausted,
       "at most 5000"},
      {"user field, no grid", {"track", {{"interface", 1}, {"field", 2}}}, "", absl::StatusCode::kInvalidArgument,
       "none was uploaded"},
      {"grid without a user field", {"track", {{"interface", 1}}}, "", absl::StatusCode::kInvalidArgument,
       "only the track method with field=2", "# vtk DataFile Version 3.0\n"},
      {"grid not VTK", {"track", {{"interface", 1}, {"field", 2}}}, "", absl::StatusCode::kInvalidArgument,
       "not a legacy VTK file", "P3 2 2"},
  };
  for (const Case& c : cases) {
    auto r = s.Submit(c.spec, c.input, c.velocity);
    ASSERT_FALSE(r.ok()) << c.what << " was accepted";
    EXPECT_EQ(r.status().code(), c.code) << c.what << ": " << r.status();
    EXPECT_NE(std::string(r.status().message()).find(c.fragment), std::string::npos) << c.what << ": " << r.status();
  }
  EXPECT_TRUE(s.List().empty());  // Nothing half-accepted.
}

TEST_F(JobServiceTest, FullQueueIsRefusedAndCancelStopsARunningJob) {
  options_.max_queue = 1;
  JobService& s = Open();
  const std::string big = Encode(testing::TorusCloud(300000, 1.0, 0.3));
  auto first = s.Submit({"iamls", {}}, big);
  ASSERT_TRUE(first.ok());
  WaitUntil(first->id, [](const JobRecord& r) { return r.state != JobState::kQueued; });
  auto second = s.Submit({"iamls", {}}, big);
  ASSERT_TRUE(second.ok()) << second.status();
  auto third = s.Submit({"iamls", {}}, big);
  EXPECT_EQ(third.status().code(), absl::StatusCode::kResourceExhausted);

  ASSERT_TRUE(s.Cancel(second->id).ok());
  EXPECT_EQ(s.Get(second->id)->state, JobState::kCancelled);  // Queued: cancelled at once.
  ASSERT_TRUE(s.Cancel(first->id).ok());
  const JobRecord stopped = WaitTerminal(first->id);
  EXPECT_EQ(stopped.state, JobState::kCancelled);
  EXPECT_EQ(s.Cancel(first->id).status().code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(s.Delete(first->id).ok());
  EXPECT_EQ(s.Get(first->id).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(JobServiceTest, JobsSurviveARestart) {
  JobService& s = Open();
  auto job = s.Submit({"iamls", {{"iterations", 2}}}, Encode(testing::SphereCloud(3000)));
  ASSERT_TRUE(job.ok());
  const std::string id = job->id;
  ASSERT_EQ(WaitTerminal(id).state, JobState::kSucceeded);
  JobService& reopened = Open();
  auto again = reopened.Get(id);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->state, JobState::kSucceeded);
  EXPECT_EQ(again->spec.parameters.at("iterations"), 2);
  EXPECT_FALSE(again->statistics.empty());
  EXPECT_TRUE(reopened.ResultPath(id, "mesh.drc").ok());
}

TEST_F(JobServiceTest, PreviewsAreCheckedDrawnAndSurviveARestart) {
  JobService& s = Open();
  const std::string input = Encode(testing::SphereCloud(3000));
  JobSpec spec{"iamls", {{"iterations", 2}}};
  spec.preview.enabled = true;
  spec.preview.render.color_attribute = "degree";  // Only PU meshes carry it.
  auto refused = s.Submit(spec, input);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("no attribute 'degree'"), std::string_view::npos) << refused.status();
  spec.preview.render.color_attribute.clear();
  spec.preview.render.width = 5;
  EXPECT_EQ(s.Submit(spec, input).status().code(), absl::StatusCode::kInvalidArgument);

  spec.preview.render.width = 96;
  spec.preview.render.height = 64;
  spec.preview.render.camera.up = render::UpAxis::kY;
  spec.preview.render.camera.azimuth_deg = 10;
  spec.preview.render.wireframe = true;
  auto job = s.Submit(spec, input);
  ASSERT_TRUE(job.ok()) << job.status();
  const JobRecord done = WaitTerminal(job->id);
  ASSERT_EQ(done.state, JobState::kSucceeded) << done.error;
  EXPECT_NE(std::find(done.results.begin(), done.results.end(), "preview.png"), done.results.end());
  auto path = s.ResultPath(job->id, "preview.png");
  ASSERT_TRUE(path.ok());
  auto png = io::ReadFileBytes(*path);
  ASSERT_TRUE(png.ok());
  // PNG signature, then the IHDR chunk: big-endian width and height at bytes 16 and 20.
  ASSERT_GT(png->size(), 24u);
  EXPECT_EQ(png->substr(0, 8), std::string("\x89PNG\r\n\x1a\n", 8));
  auto be32 = [&](size_t at) {
    uint32_t v = 0;
    for (size_t i = 0; i < 4; ++i) v = v << 8 | static_cast<uint8_t>((*png)[at + i]);
    return v;
  };
  EXPECT_EQ(be32(16), 96u);
  EXPECT_EQ(be32(20), 64u);

  JobService& reopened = Open();
  auto again = reopened.Get(job->id);
  ASSERT_TRUE(again.ok());
  const PreviewSpec& kept = again->spec.preview;
  EXPECT_TRUE(kept.enabled);
  EXPECT_EQ(kept.render.width, 96);
  EXPECT_EQ(kept.render.height, 64);
  EXPECT_EQ(kept.render.camera.up, render::UpAxis::kY);
  EXPECT_EQ(kept.render.camera.azimuth_deg, 10);
  EXPECT_TRUE(kept.render.wireframe);
  EXPECT_FALSE(reopened.Get(job->id).value().spec.preview.render.transparent);
}

TEST_F(JobServiceTest, DatabasesFromBeforePreviewsStillOpen) {
  // The table as the first releases wrote it, with one finished job.
  {
    sqlite3* db = nullptr;
    std::filesystem::create_directories(dir_);
    ASSERT_EQ(sqlite3_open((dir_ / "jobs.db").string().c_str(), &db), SQLITE_OK);
    const char* sql =
        "CREATE TABLE jobs (id TEXT PRIMARY KEY, method TEXT, parameters TEXT, mesh_bits INTEGER, state INTEGER, "
        "stage TEXT, attempts INTEGER, error TEXT, created_ms INTEGER, updated_ms INTEGER, input_points INTEGER, "
        "input_bytes INTEGER, statistics TEXT, results TEXT);"
        "INSERT INTO jobs VALUES ('cccc', 'iamls', 'iterations=3;', 16, 2, 'done', 1, '', 1, 2, 3000, 100, "
        "'wall_seconds=1;', 'mesh.drc;');";
    EXPECT_EQ(sqlite3_exec(db, sql, nullptr, nullptr, nullptr), SQLITE_OK);
    sqlite3_close(db);
  }
  JobService& s = Open();
  auto old = s.Get("cccc");
  ASSERT_TRUE(old.ok()) << old.status();
  EXPECT_EQ(old->state, JobState::kSucceeded);
  EXPECT_EQ(old->spec.parameters.at("iterations"), 3);
  EXPECT_FALSE(old->spec.preview.enabled);
}

TEST_F(JobServiceTest, InterruptedJobsRunAgainOnceThenFail) {
  // Simulate the records a killed server leaves behind: jobs marked running.
  std::filesystem::create_directories(dir_ / "jobs" / "aaaa");
  std::filesystem::create_directories(dir_ / "jobs" / "bbbb");
  const std::string input = Encode(testing::SphereCloud(3000));
  ASSERT_TRUE(io::WriteFileAtomically((dir_ / "jobs" / "aaaa" / "input.drc").string(), input).ok());
  ASSERT_TRUE(io::WriteFileAtomically((dir_ / "jobs" / "bbbb" / "input.drc").string(), input).ok());
  {
    auto store = JobStore::Open((dir_ / "jobs.db").string());
    ASSERT_TRUE(store.ok());
    JobRecord once;
    once.id = "aaaa";
    once.spec.method = "iamls";
    once.state = JobState::kRunning;
    once.attempts = 1;
    JobRecord twice = once;
    twice.id = "bbbb";
    twice.attempts = 2;
    ASSERT_TRUE((*store)->Put(once).ok());
    ASSERT_TRUE((*store)->Put(twice).ok());
  }
  JobService& s = Open();
  EXPECT_EQ(s.Get("bbbb")->state, JobState::kFailed);
  EXPECT_NE(s.Get("bbbb")->error.find("giving up"), std::string::npos);
  const JobRecord resumed = WaitTerminal("aaaa");
  EXPECT_EQ(resumed.state, JobState::kSucceeded) << resumed.error;
  EXPECT_EQ(resumed.attempts, 2);
}

TEST_F(JobServiceTest, ShutdownRequeuesTheRunningJob) {
  JobService& s = Open();
  auto job = s.Submit({"iamls", {}}, Encode(testing::TorusCloud(100000, 1.0, 0.3)));
  ASSERT_TRUE(job.ok());
  WaitUntil(job->id, [](const JobRecord& r) { return r.state == JobState::kRunning; });
  s.Shutdown();
  EXPECT_EQ(s.Get(job->id)->state, JobState::kQueued);
  EXPECT_EQ(s.Get(job->id)->attempts, 0);
  JobService& reopened = Open();
  EXPECT_EQ(WaitTerminal(job->id).state, JobState::kSucceeded);
  (void)reopened;
}

}  // namespace
}  // namespace lsqsurf::jobs
