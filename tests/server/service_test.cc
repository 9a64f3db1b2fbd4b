// ReconstructionService in this process, on a loopback port, with jobs held by a latch: the
// calls a client makes while a job is certainly running, and the limits it can discover.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <set>
#include <sstream>

#include "client/client.h"
#include "server/metrics.h"
#include "server/server.h"
#include "tests/latch_kind.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/io/mesh_part.h"
#include "worker/io/volume_codec.h"
#include "worker/volume/synthetic.h"

namespace lsqsurf::server {
namespace {

class ServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-service");
    options_.data_dir = dir_.string();
    options_.max_queue = 1;
    options_.max_points = 123456;
    options_.kind_overrides["iamls"] = &latch_;
    auto jobs = jobs::JobService::Open(options_);
    ASSERT_TRUE(jobs.ok()) << jobs.status();
    jobs_ = *std::move(jobs);
    auto server = Server::Start(*jobs_, {});
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = *std::move(server);
    client_ = std::make_unique<client::Client>(server_->address());
    auto input = io::EncodeDracoPointCloud(testing::SphereCloud(2000), {});
    ASSERT_TRUE(input.ok());
    input_ = *input;
    spec_.mutable_iamls()->set_iterations(2);
  }
  void TearDown() override {
    latch_.Release();
    server_.reset();  // Before the job service it serves.
    jobs_.reset();
    std::filesystem::remove_all(dir_);
  }

  std::filesystem::path dir_;
  jobs::JobServiceOptions options_;
  testing::LatchKind latch_;
  std::unique_ptr<jobs::JobService> jobs_;
  std::unique_ptr<Server> server_;
  std::unique_ptr<client::Client> client_;
  std::string input_;
  v1::JobSpec spec_;
};

// Metric labels come from a fixed set: a stage's numbers, which users' parameters choose, go.
TEST(StageLabel, KeepsTheWordsAndDropsTheNumbers) {
  EXPECT_EQ(StageLabel("volume: isosurface 0.25: tracking surface"), "volume: isosurface #: tracking surface");
  EXPECT_EQ(StageLabel("volume: isosurface -1e-07"), "volume: isosurface #");
  EXPECT_EQ(StageLabel("pu: fitting level 12"), "pu: fitting level #");
  EXPECT_EQ(StageLabel("iamls: extracting surface"), "iamls: extracting surface");
  EXPECT_EQ(StageLabel("pu: J1a leaves"), "pu: J1a leaves");
  EXPECT_EQ(StageLabel("volume: isosurface 0.1"), StageLabel("volume: isosurface 123456.75"));
}

TEST_F(ServiceTest, ARunningJobCanBeCancelledButNotDeletedOrFetched) {
  auto job = client_->Submit(spec_, input_);
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->spec().iamls().iterations(), 2);
  latch_.WaitStarted(1);
  EXPECT_EQ(client_->Delete(job->id()).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(client_->Fetch(job->id(), "").status().code(), absl::StatusCode::kFailedPrecondition);
  auto requested = client_->Cancel(job->id());
  ASSERT_TRUE(requested.ok());
  EXPECT_EQ(requested->state(), v1::JOB_STATE_RUNNING);  // CANCELLED follows.
  std::vector<v1::JobState> seen;
  auto last = client_->Watch(job->id(), [&](const v1::Job& j) { seen.push_back(j.state()); });
  ASSERT_TRUE(last.ok()) << last.status();
  EXPECT_EQ(last->state(), v1::JOB_STATE_CANCELLED);
  EXPECT_EQ(seen.back(), v1::JOB_STATE_CANCELLED);
  EXPECT_EQ(client_->Cancel(job->id()).status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(client_->Delete(job->id()).ok());
  EXPECT_EQ(client_->Get(job->id()).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(ServiceTest, AFullQueueAnswersResourceExhausted) {
  auto running = client_->Submit(spec_, input_);
  ASSERT_TRUE(running.ok());
  latch_.WaitStarted(1);
  auto queued = client_->Submit(spec_, input_);
  ASSERT_TRUE(queued.ok()) << queued.status();
  EXPECT_EQ(queued->state(), v1::JOB_STATE_QUEUED);
  const auto refused = client_->Submit(spec_, input_);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.status().message().find("queue is full"), std::string_view::npos) << refused.status();
  auto cancelled = client_->Cancel(queued->id());
  ASSERT_TRUE(cancelled.ok());
  EXPECT_EQ(cancelled->state(), v1::JOB_STATE_CANCELLED);  // Queued jobs end at once.
}

TEST_F(ServiceTest, WatchersSeeEveryStateAndTheResultStreamsBack) {
  auto job = client_->Submit(spec_, input_);
  ASSERT_TRUE(job.ok());
  latch_.WaitStarted(1);
  latch_.Release();
  auto last = client_->Watch(job->id());
  ASSERT_TRUE(last.ok());
  EXPECT_EQ(last->state(), v1::JOB_STATE_SUCCEEDED);
  EXPECT_EQ(last->attempts(), 1);
  auto bytes = client_->Fetch(job->id(), "held.txt");
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  EXPECT_EQ(*bytes, "released");
  EXPECT_EQ(client_->Fetch(job->id(), "mesh.drc").status().code(), absl::StatusCode::kNotFound);
}

TEST_F(ServiceTest, LimitsAreDiscoverable) {
  auto info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->max_points(), 123456);
  EXPECT_EQ(info->max_queue(), 1);
  EXPECT_EQ(info->min_points(), options_.min_points);
  EXPECT_EQ(info->max_upload_bytes(), options_.max_input_bytes);
  EXPECT_EQ(info->max_chunk_bytes(), static_cast<int64_t>(ReconstructionService::kMaxChunkBytes));
  EXPECT_FALSE(info->version().empty());
  auto too_many = io::EncodeDracoPointCloud(testing::SphereCloud(200000), {});
  ASSERT_TRUE(too_many.ok());
  v1::JobSpec pu;
  pu.mutable_pu();
  EXPECT_EQ(client_->Submit(pu, *too_many).status().code(), absl::StatusCode::kResourceExhausted);
}

// A cloud sent in parts, each its own Draco stream, is one job; a PU job over tile_points reads
// the parts one at a time and delivers one closed mesh.
TEST_F(ServiceTest, ACloudUploadedInPartsIsOneJob) {
  io::DracoOptions exact;
  exact.position_bits = 0;
  const auto cloud = std::make_shared<const core::PointCloud>(testing::DrilledBlockCloud(12'000, 2.0, 0.6, 0.3, 0.3));
  v1::JobSpec pu;
  pu.mutable_pu()->set_tile_points(3000);
  pu.mutable_pu()->set_support_cap(16);
  auto job = client_->SubmitParts(pu, client::CloudParts(cloud, exact, 2500));
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->input_points(), 12'000);
  auto done = client_->Watch(job->id());
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  std::map<std::string, double> stats;
  for (const auto& s : done->statistics()) stats[s.name()] = s.value();
  EXPECT_EQ(stats["input_streamed"], 1);
  EXPECT_GE(stats["tiles"], 4);
  // The mesh comes back in parts too, joined into a file as they come.
  const std::vector<std::string> parts = client::MeshParts(*done);
  EXPECT_EQ(static_cast<double>(parts.size()), stats["mesh_parts"]);
  const std::string path = (dir_ / "block.ply").string();
  ASSERT_TRUE(client::WriteMeshParts(
                  parts.size(), [&](size_t i) { return client_->Fetch(job->id(), parts[i]); }, path)
                  .ok());
  auto mesh = io::ReadMeshFile(path);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_EQ(static_cast<double>(mesh->faces.size()), stats["triangles"]);
  const core::MeshTopology topology = core::AnalyzeTopology(core::WeldByPosition(*mesh));
  EXPECT_TRUE(topology.watertight());
  EXPECT_EQ(topology.euler_characteristic(), 0);  // One hole through the block.

  // All parts together count against max_points, though each is below it.
  const auto big = std::make_shared<const core::PointCloud>(testing::SphereCloud(200'000));
  const absl::Status too_many = client_->SubmitParts(pu, client::CloudParts(big, {}, 100'000)).status();
  EXPECT_EQ(too_many.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(too_many.message().find("parts 0 to 1 of the cloud hold 200000 points"), std::string::npos) << too_many;

  // The server counts the parts' declared points as each ends (a client need not check first):
  // the second part of 100,000 is refused as it ends, before any more could come.
  auto stub = v1::Reconstruction::NewStub(grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials()));
  {
    auto part = io::EncodeDracoPointCloud(testing::SphereCloud(100'000), {});
    ASSERT_TRUE(part.ok());
    grpc::ClientContext context;
    v1::Job response;
    auto writer = stub->SubmitJob(&context, &response);
    v1::SubmitJobRequest request;
    *request.mutable_spec() = pu;
    ASSERT_TRUE(writer->Write(request));
    for (int k = 0; k < 2; ++k) {
      v1::SubmitJobRequest chunk;
      chunk.set_input_chunk(*part);
      v1::SubmitJobRequest end;
      end.set_input_part_end(true);
      if (!writer->Write(chunk) || !writer->Write(end)) break;
    }
    writer->WritesDone();
    const grpc::Status refused = writer->Finish();
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(refused.error_message().find("input parts 0 to 1 declare 200000 points"), std::string::npos)
        << refused.error_message();
  }

  // A part must have chunks before it ends.
  grpc::ClientContext context;
  v1::Job response;
  auto writer = stub->SubmitJob(&context, &response);
  v1::SubmitJobRequest request;
  *request.mutable_spec() = pu;
  ASSERT_TRUE(writer->Write(request));
  request.set_input_part_end(true);
  (void)writer->Write(request);
  writer->WritesDone();
  const grpc::Status ended_empty = writer->Finish();
  EXPECT_EQ(ended_empty.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(ended_empty.error_message().find("input part 0 ended before any of its chunks"), std::string::npos)
      << ended_empty.error_message();
}

// The mesh parts of a running job can be fetched through the API before it ends (a partial
// result); its other artifacts cannot.
TEST_F(ServiceTest, ARunningJobsMeshPartsAreFetchedBeforeItEnds) {
  const std::vector<core::Vec3f> triangle = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  const std::vector<std::array<int64_t, 3>> face = {{0, 1, 2}};
  const std::string part = io::EncodeMeshPart(0, triangle, {}, {}, face);
  latch_.WriteBeforeHolding(jobs::MeshPartArtifact(0), part);
  auto job = client_->Submit(spec_, input_);
  ASSERT_TRUE(job.ok()) << job.status();
  latch_.WaitStarted(1);
  auto record = jobs_->Get(job->id());
  while (record.ok() && record->results.empty()) {
    record = jobs_->WaitForChange(job->id(), record->version, std::chrono::seconds(1));
  }
  auto running = client_->Get(job->id());
  ASSERT_TRUE(running.ok()) << running.status();
  EXPECT_EQ(running->state(), v1::JOB_STATE_RUNNING);
  const std::vector<std::string> parts = client::MeshParts(*running);
  ASSERT_EQ(parts, std::vector<std::string>{jobs::MeshPartArtifact(0)});
  auto fetched = client_->Fetch(job->id(), parts[0]);
  ASSERT_TRUE(fetched.ok()) << fetched.status();
  EXPECT_EQ(*fetched, part);
  EXPECT_EQ(client_->Fetch(job->id(), "").status().code(), absl::StatusCode::kFailedPrecondition);
  const std::string path = (dir_ / "partial.ply").string();
  ASSERT_TRUE(client::WriteMeshParts(
                  1, [&](size_t i) { return client_->Fetch(job->id(), parts[i]); }, path)
                  .ok());
  auto mesh = io::ReadMeshFile(path);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_EQ(mesh->vertices, triangle);
  EXPECT_EQ(mesh->faces.size(), 1u);
  latch_.Release();
}

TEST_F(ServiceTest, BadSpecsAreRefusedBeforeTheUpload) {
  v1::JobSpec bad;
  bad.mutable_pu()->set_noise_level(-0.5);
  const auto refused = client_->Submit(bad, input_);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("noise_level"), std::string_view::npos) << refused.status();
  auto listed = client_->List(10);
  ASSERT_TRUE(listed.ok());
  EXPECT_EQ(listed->jobs_size(), 0);
}

TEST_F(ServiceTest, MethodsListTheirParametersWithDefaults) {
  auto methods = client_->ListMethods();
  ASSERT_TRUE(methods.ok());
  std::vector<std::string> names;
  for (const auto& m : methods->methods()) names.push_back(m.name());
  EXPECT_EQ(names, (std::vector<std::string>{"iamls", "pu", "ramls", "apss", "aamls", "imls", "csg", "edit", "track",
                                             "volume", "probe"}));
  for (const auto& m : methods->methods()) {
    EXPECT_GT(m.parameters_size(), 0) << m.name();
    for (const auto& p : m.parameters()) {
      EXPECT_FALSE(p.help().empty()) << m.name() << "." << p.name();
    }
  }
}

}  // namespace
}  // namespace lsqsurf::server

namespace lsqsurf::server {
namespace {

// A volume job end to end through the wire: the compressed uploads, the field, the isosurface.
TEST_F(ServiceTest, AVolumeMeshBecomesAnIsosurfaceAndBadVolumesAreRefused) {
  volume::VolumeMesh mesh = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 9, 0.3, 2);
  volume::SampleField(mesh, volume::Franke3d());
  const std::vector<std::string> fields = {"franke"};
  auto vertices = io::EncodeVolumeVertices(mesh, fields, {});
  ASSERT_TRUE(vertices.ok());
  const std::string cells = io::EncodeCellStream(mesh);
  v1::JobSpec spec;
  spec.mutable_volume()->set_field("franke");
  spec.mutable_volume()->add_iso(0.4);
  auto job = client_->Submit(spec, *vertices, {}, cells);
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->input_points(), static_cast<int64_t>(mesh.vertex_count()));
  auto done = client_->Watch(job->id());
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  auto bytes = client_->Fetch(job->id(), "");
  ASSERT_TRUE(bytes.ok());
  auto surface = io::DecodeDracoMesh(*bytes);
  ASSERT_TRUE(surface.ok());
  EXPECT_GT(surface->faces.size(), 100u);
  bool chosen = false;
  for (const auto& s : done->statistics()) chosen |= s.name() == "epsilon_chosen_by_cross_validation" && s.value() == 1;
  EXPECT_TRUE(chosen);
  // A picture of the field whose sampled grid would pass the server's bound is refused before it
  // is sampled (512³ points take 2 GiB; the default bound is 1 GiB).
  v1::RenderOptions fine_grid;
  fine_grid.set_volume_resolution(512);
  const absl::Status too_big = client_->Render(job->id(), "field.lqvf", fine_grid).status();
  EXPECT_EQ(too_big.code(), absl::StatusCode::kResourceExhausted) << too_big;
  EXPECT_NE(too_big.message().find("--max-render-mib"), std::string::npos) << too_big;

  // A cell pointing past the vertices, a field that is not there, a missing cell stream's
  // corruption: INVALID_ARGUMENT with the reason; too many cells: RESOURCE_EXHAUSTED.
  volume::VolumeMesh broken = mesh;
  broken.cell_vertices[5] = 100000;
  auto out_of_range = client_->Submit(spec, *vertices, {}, io::EncodeCellStream(broken));
  ASSERT_FALSE(out_of_range.ok());
  EXPECT_EQ(out_of_range.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(out_of_range.status().message().find("refers to vertex 100000"), std::string::npos)
      << out_of_range.status();
  v1::JobSpec wrong_field = spec;
  wrong_field.mutable_volume()->set_field("pressure");
  auto missing = client_->Submit(wrong_field, *vertices, {}, cells);
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.status().message().find("franke (scalar)"), std::string::npos) << missing.status();
  auto corrupt = client_->Submit(spec, *vertices, {}, cells.substr(0, cells.size() - 3));
  EXPECT_EQ(corrupt.status().code(), absl::StatusCode::kInvalidArgument) << corrupt.status();
  // The same vertices coded with Draco's KD-tree method come back in another order, which the
  // cells cannot follow: refused with that reason, not as inverted cells.
  core::PointCloud reordering;
  reordering.positions = mesh.positions;
  reordering.attributes.push_back({"franke", mesh.FindField("franke")->values});
  auto kd_coded = io::EncodeDracoPointCloud(reordering, io::DracoOptions{.speed = 5});
  ASSERT_TRUE(kd_coded.ok()) << kd_coded.status();
  auto kd_refused = client_->Submit(spec, *kd_coded, {}, cells);
  ASSERT_FALSE(kd_refused.ok());
  EXPECT_EQ(kd_refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(kd_refused.status().message().find("KD-tree"), std::string::npos) << kd_refused.status();
  // An iso-value beyond every value of the field at the vertices would extract nothing: refused
  // at submission with the field's range.
  double highest = -1e300;
  for (float v : mesh.FindField("franke")->values) highest = std::max<double>(highest, v);
  v1::JobSpec beyond = spec;
  beyond.mutable_volume()->add_iso(highest + 0.5);
  auto empty_level = client_->Submit(beyond, *vertices, {}, cells);
  ASSERT_FALSE(empty_level.ok());
  EXPECT_EQ(empty_level.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(empty_level.status().message().find("lies outside the values of 'franke'"), std::string::npos)
      << empty_level.status();
  // A picture of the kept field, drawn by the CPU ray caster from a sampled grid whose error is
  // reported.
  v1::RenderOptions view;
  view.set_width(64);
  view.set_height(64);
  auto frame = client_->Render(job->id(), "field.lqvf", view);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(frame->png().substr(1, 3), "PNG");
  EXPECT_FALSE(frame->renderer().empty());
  EXPECT_GT(frame->grid_rms_error(), 0);
  EXPECT_LT(frame->grid_max_error(), 0.05 * (frame->color_max() - frame->color_min()));
  view.set_opacity("1:0,0:1");
  EXPECT_EQ(client_->Render(job->id(), "field.lqvf", view).status().code(), absl::StatusCode::kInvalidArgument);

  // Probes of the finished job: points (one outside the domain) and a grid.
  v1::JobSpec probe;
  probe.mutable_probe()->set_source(job->id());
  core::PointCloud points;
  points.positions = {{0.3f, 0.4f, 0.5f}, {0.6f, 0.5f, 0.45f}, {1.5f, 0.5f, 0.5f}};
  io::DracoOptions exact;
  exact.position_bits = 0;
  exact.speed = 10;
  auto probe_points = io::EncodeDracoPointCloud(points, exact);
  ASSERT_TRUE(probe_points.ok());
  auto probed = client_->Submit(probe, *probe_points);
  ASSERT_TRUE(probed.ok()) << probed.status();
  auto probe_done = client_->Watch(probed->id());
  ASSERT_TRUE(probe_done.ok());
  ASSERT_EQ(probe_done->state(), v1::JOB_STATE_SUCCEEDED) << probe_done->error();
  auto csv = client_->Fetch(probed->id(), "values.csv");
  ASSERT_TRUE(csv.ok());
  std::istringstream rows(*csv);
  std::string line;
  std::getline(rows, line);
  EXPECT_EQ(line, "x,y,z,value,gx,gy,gz");
  for (const core::Vec3f& p : points.positions) {
    ASSERT_TRUE(std::getline(rows, line));
    double x, y, z;
    char comma;
    std::istringstream row(line);
    row >> x >> comma >> y >> comma >> z >> comma;
    EXPECT_NEAR(x, p.x(), 1e-6);
    if (p.x() > 1) {
      EXPECT_TRUE(line.ends_with(",,,,")) << line;  // Outside the cells: no value.
      continue;
    }
    double value;
    row >> value;
    EXPECT_NEAR(value, volume::Franke3d().value(p.cast<double>()), 0.02) << line;  // A 9^3 mesh.
  }
  probe.mutable_probe()->set_grid("5x4x3");
  auto grid_job = client_->Submit(probe, "");
  ASSERT_TRUE(grid_job.ok()) << grid_job.status();
  auto grid_done = client_->Watch(grid_job->id());
  ASSERT_TRUE(grid_done.ok());
  ASSERT_EQ(grid_done->state(), v1::JOB_STATE_SUCCEEDED) << grid_done->error();
  auto vti = client_->Fetch(grid_job->id(), "field.vti");
  ASSERT_TRUE(vti.ok());
  EXPECT_NE(vti->find("WholeExtent=\"0 4 0 3 0 2\""), std::string::npos);
  // A source that is no job is refused at once: one that is not an id at all, and a missing one.
  v1::JobSpec orphan;
  orphan.mutable_probe()->set_source("no-such-job");
  orphan.mutable_probe()->set_grid("4x4x4");
  EXPECT_EQ(client_->Submit(orphan, "").status().code(), absl::StatusCode::kInvalidArgument);
  const std::string no_job(32, '0');
  orphan.mutable_probe()->set_source(no_job);
  const absl::Status no_source = client_->Submit(orphan, "").status();
  EXPECT_EQ(no_source.code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(no_source.message(), "no job with id '" + no_job + "'");
  // A job that has no field: it fails with the reason.
  orphan.mutable_probe()->set_source(probed->id());
  auto orphan_job = client_->Submit(orphan, "");
  ASSERT_TRUE(orphan_job.ok()) << orphan_job.status();
  auto orphan_done = client_->Watch(orphan_job->id());
  ASSERT_TRUE(orphan_done.ok());
  EXPECT_EQ(orphan_done->state(), v1::JOB_STATE_FAILED);
  EXPECT_NE(orphan_done->error().find("no kept volume field"), std::string::npos) << orphan_done->error();

  volume::VolumeMesh huge = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 60, 0, 2);
  volume::SampleField(huge, volume::Franke3d());
  auto huge_vertices = io::EncodeVolumeVertices(huge, fields, {});
  ASSERT_TRUE(huge_vertices.ok());
  auto too_many = client_->Submit(spec, *huge_vertices, {}, io::EncodeCellStream(huge));
  EXPECT_EQ(too_many.status().code(), absl::StatusCode::kResourceExhausted) << too_many.status();
}

// A PU job keeps its function; a csg job cuts it with a box by reference, without an upload, and
// the result is the closed half ball. Bad expressions and references are refused with reasons.
TEST_F(ServiceTest, CsgAndEditReuseAKeptPuResult) {
  auto ball = io::EncodeDracoPointCloud(testing::SphereCloud(20'000), {});
  ASSERT_TRUE(ball.ok());
  v1::JobSpec pu;
  pu.mutable_pu();
  auto fitted = client_->Submit(pu, *ball);
  ASSERT_TRUE(fitted.ok()) << fitted.status();
  auto fitted_done = client_->Watch(fitted->id());
  ASSERT_TRUE(fitted_done.ok());
  ASSERT_EQ(fitted_done->state(), v1::JOB_STATE_SUCCEEDED) << fitted_done->error();
  EXPECT_NE(std::find(fitted_done->results().begin(), fitted_done->results().end(), "function.lqpu"),
            fitted_done->results().end());

  v1::JobSpec cut;
  cut.mutable_csg()->set_expression("difference(job:" + fitted->id() + " box(min=0,-2,-2 max=2,2,2))");
  auto job = client_->Submit(cut, "");
  ASSERT_TRUE(job.ok()) << job.status();
  auto done = client_->Watch(job->id());
  ASSERT_TRUE(done.ok());
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  auto bytes = client_->Fetch(job->id(), "");
  ASSERT_TRUE(bytes.ok());
  auto mesh = io::DecodeDracoMesh(*bytes);  // Another decoder's view: merged by position.
  ASSERT_TRUE(mesh.ok());
  const core::MeshTopology topology = core::AnalyzeTopology(core::WeldByPosition(*mesh));
  EXPECT_TRUE(topology.watertight());
  EXPECT_EQ(topology.components, 1);
  EXPECT_NEAR(core::EnclosedVolume(*mesh), 2 * M_PI / 3, 0.01);
  // The smallest-angle histogram: twelve 5° bins that share out every face.
  double shares = 0;
  int bins = 0;
  for (const auto& s : done->statistics()) {
    if (s.name().rfind("min_angle_share_", 0) != 0) continue;
    ++bins;
    EXPECT_GE(s.value(), 0.0);
    shares += s.value();
  }
  EXPECT_EQ(bins, 12);
  EXPECT_NEAR(shares, 1.0, 1e-9);

  // A local edit of the same kept function: a new job, closed, and editable again.
  v1::JobSpec edit;
  edit.mutable_edit()->set_source(fitted->id());
  edit.mutable_edit()->set_center_x(1.0);
  edit.mutable_edit()->set_radius(0.2);
  edit.mutable_edit()->set_degree(1);
  auto edited = client_->Submit(edit, "");
  ASSERT_TRUE(edited.ok()) << edited.status();
  auto edited_done = client_->Watch(edited->id());
  ASSERT_TRUE(edited_done.ok());
  ASSERT_EQ(edited_done->state(), v1::JOB_STATE_SUCCEEDED) << edited_done->error();
  std::map<std::string, double> edit_stats;
  for (const auto& s : edited_done->statistics()) edit_stats[s.name()] = s.value();
  EXPECT_GT(edit_stats["fits_replaced"], 0);
  EXPECT_GT(edit_stats["edit_reach"], 0.2);
  EXPECT_EQ(edit_stats["boundary_edges"], 0);
  EXPECT_EQ(edit_stats["components"], 1);
  edit.mutable_edit()->set_source(edited->id());
  edit.mutable_edit()->set_action(v1::EditParams::ACTION_REMOVE);
  edit.mutable_edit()->set_radius(0.4);
  auto removed = client_->Submit(edit, "");
  ASSERT_TRUE(removed.ok()) << removed.status();
  auto removed_done = client_->Watch(removed->id());
  ASSERT_TRUE(removed_done.ok());
  ASSERT_EQ(removed_done->state(), v1::JOB_STATE_SUCCEEDED) << removed_done->error();
  std::map<std::string, double> removed_stats;
  for (const auto& s : removed_done->statistics()) removed_stats[s.name()] = s.value();
  EXPECT_GT(removed_stats["points_removed"], 0);
  EXPECT_GT(removed_stats["boundary_edges"], 0);  // The hole.
  v1::JobSpec no_ball;
  no_ball.mutable_edit()->set_source(fitted->id());
  EXPECT_EQ(client_->Submit(no_ball, "").status().code(), absl::StatusCode::kInvalidArgument);

  v1::JobSpec malformed;
  malformed.mutable_csg()->set_expression("difference(job:x sphre(r=1))");
  auto refused = client_->Submit(malformed, "");
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("column 18"), std::string::npos) << refused.status();
  v1::JobSpec with_upload = cut;
  EXPECT_EQ(client_->Submit(with_upload, input_).status().code(), absl::StatusCode::kInvalidArgument);

  // A reference to no job is refused at submission; one to a job that keeps no function fails.
  v1::JobSpec orphan;
  orphan.mutable_csg()->set_expression("union(job:no-such-job sphere(r=1))");
  EXPECT_EQ(client_->Submit(orphan, "").status().code(), absl::StatusCode::kInvalidArgument);
  const std::string missing(32, 'f');
  orphan.mutable_csg()->set_expression("union(job:" + missing + " sphere(r=1))");
  const absl::Status no_operand = client_->Submit(orphan, "").status();
  EXPECT_EQ(no_operand.code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(no_operand.message(), "no job with id '" + missing + "'");
  orphan.mutable_csg()->set_expression("union(job:" + job->id() + " sphere(r=1))");
  auto orphan_job = client_->Submit(orphan, "");
  ASSERT_TRUE(orphan_job.ok()) << orphan_job.status();
  auto orphan_done = client_->Watch(orphan_job->id());
  ASSERT_TRUE(orphan_done.ok());
  EXPECT_EQ(orphan_done->state(), v1::JOB_STATE_FAILED);
  EXPECT_NE(orphan_done->error().find("job:" + job->id()), std::string::npos) << orphan_done->error();
}

// 2,000 jobs, most with 60 KiB text parameters (111 MB of records), come back through ListJobs'
// pages: newest first, each once, every page within its job count and under 4 MiB (a listing of
// them all in one message once failed past gRPC's 16 MiB), and a token the server did not give
// is refused.
TEST(ListJobsPaging, ManyLargeJobsComeThroughThePagesNewestFirstEachOnce) {
  const auto dir = testing::FreshTestDir("lsqsurf-paging");
  testing::LatchKind latch;
  latch.Release();  // Jobs run through at once.
  jobs::JobServiceOptions options;
  options.data_dir = dir.string();
  constexpr int kJobs = 2000;
  options.max_queue = kJobs;
  options.kind_overrides["iamls"] = &latch;
  options.kind_overrides["volume"] = &latch;
  auto jobs = jobs::JobService::Open(options);
  ASSERT_TRUE(jobs.ok()) << jobs.status();
  auto server = Server::Start(**jobs, {});
  ASSERT_TRUE(server.ok()) << server.status();
  client::Client client((*server)->address());
  auto input = io::EncodeDracoPointCloud(testing::SphereCloud(200), {});
  ASSERT_TRUE(input.ok());
  std::set<std::string> submitted;
  v1::JobSpec small;
  small.mutable_iamls();
  v1::JobSpec large;
  large.mutable_volume()->set_field("f");
  large.mutable_volume()->set_color_by(std::string(60 << 10, 'c'));
  for (int i = 0; i < kJobs; ++i) {
    auto job = client.Submit(i < 150 ? small : large, *input);
    ASSERT_TRUE(job.ok()) << job.status();
    submitted.insert(job->id());
  }

  auto first = client.ListPage(0, "");
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_LT(first->jobs_size(), 100);  // A hundred of the (newest, large) ones take 6.1 MB.
  EXPECT_GT(first->jobs_size(), 40);
  EXPECT_LE(first->ByteSizeLong(), size_t{(4 << 20) + (64 << 10)});
  EXPECT_FALSE(first->next_page_token().empty());

  std::vector<v1::Job> seen;
  std::string token;
  int pages = 0;
  do {
    auto page = client.ListPage(50, token);
    ASSERT_TRUE(page.ok()) << page.status();
    EXPECT_LE(page->jobs_size(), 50);
    EXPECT_LE(page->ByteSizeLong(), size_t{(4 << 20) + (64 << 10)});
    seen.insert(seen.end(), page->jobs().begin(), page->jobs().end());
    token = page->next_page_token();
    ++pages;
  } while (!token.empty() && pages < 100);
  EXPECT_EQ(pages, kJobs / 50);
  std::set<std::string> listed;
  for (size_t i = 0; i < seen.size(); ++i) {
    listed.insert(seen[i].id());
    if (i > 0) {
      EXPECT_TRUE(std::pair(seen[i - 1].created_ms(), seen[i - 1].id()) > std::pair(seen[i].created_ms(), seen[i].id()))
          << i;
    }
  }
  EXPECT_EQ(seen.size(), submitted.size());
  EXPECT_EQ(listed, submitted);
  auto all = client.List(0);
  ASSERT_TRUE(all.ok()) << all.status();
  EXPECT_EQ(all->jobs_size(), kJobs);
  EXPECT_EQ(client.ListPage(10, "17.not-a-job").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client.ListPage(10, "nonsense").status().code(), absl::StatusCode::kInvalidArgument);
  server->reset();
  jobs->reset();
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace lsqsurf::server
