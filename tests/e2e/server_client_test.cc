// End-to-end: the real lsqsurfd on a free loopback port, driven by the real lsqsurf client.
#include <fcntl.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <numbers>
#include <sstream>
#include <thread>

#include "client/client.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "stb_image.h"
#include "tests/e2e/harness.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/io/files.h"
#include "worker/io/pts_ptx.h"
#include "worker/io/volume_formats.h"
#include "worker/volume/synthetic.h"

namespace lsqsurf {
namespace {

namespace fs = std::filesystem;
namespace v1 = lsqsurf::v1;

using testing::Client;
using testing::ClientRun;
using testing::Server;
using testing::Trim;

class EndToEnd : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-e2e");
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string WriteCloud(const std::string& name, const core::PointCloud& cloud) {
    const std::string path = (dir_ / name).string();
    EXPECT_TRUE(io::WritePointCloudFile(path, cloud).ok());
    return path;
  }
  // Submits a job that runs for minutes (a sphere through 100000 steps of rotation), so that what
  // the test does next certainly meets it queued or running; the test cancels it.
  std::string SubmitLongJob(const std::string& address) {
    v1::JobSpec spec;
    spec.mutable_track()->set_steps(100000);
    spec.mutable_track()->set_cells(32);
    auto job = client::Client(address).Submit(spec, {});
    EXPECT_TRUE(job.ok()) << job.status();
    return job.ok() ? job->id() : std::string();
  }
  // Follows the job's events until it runs (true) or ends (false).
  static bool WaitRunning(const std::string& address, const std::string& id) {
    auto stub = v1::Reconstruction::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
    grpc::ClientContext ctx;
    v1::WatchJobRequest request;
    request.set_job_id(id);
    auto reader = stub->WatchJob(&ctx, request);
    v1::JobEvent event;
    bool running = false;
    while (!running && reader->Read(&event)) running = event.job().state() == v1::JOB_STATE_RUNNING;
    ctx.TryCancel();
    (void)reader->Finish();
    return running;
  }
  fs::path dir_;
};

TEST_F(EndToEnd, ReconstructsASphereAndAnswersHealthChecks) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const std::string in = WriteCloud("sphere.ply", testing::SphereCloud(8000));
  const std::string out = (dir_ / "sphere-mesh.ply").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out);
  ASSERT_EQ(r.code, 0) << r.output;
  auto mesh = io::ReadMeshFile(out);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  const core::MeshTopology t = core::AnalyzeTopology(*mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_EQ(t.euler_characteristic(), 2);
  for (const auto& v : mesh->vertices) EXPECT_NEAR(v.norm(), 1.0f, 0.01f);
  // A summary by default; every statistic (the angle histogram among them) with --stats.
  EXPECT_NE(r.output.find(" triangles, closed, 1 component; in "), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("min_angle_share"), std::string::npos) << r.output;
  const ClientRun all = Client(server.address(), "reconstruct " + in + " -o " + out + " --stats");
  ASSERT_EQ(all.code, 0) << all.output;
  EXPECT_NE(all.output.find("min_angle_share_30_35 = "), std::string::npos) << all.output;

  const ClientRun drc = Client(server.address(), "reconstruct " + in + " -o " + (dir_ / "m.drc").string());
  ASSERT_EQ(drc.code, 0) << drc.output;
  EXPECT_TRUE(io::ReadMeshFile((dir_ / "m.drc").string()).ok());

  auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto health = grpc::health::v1::Health::NewStub(channel);
  grpc::ClientContext ctx;
  grpc::health::v1::HealthCheckRequest request;
  grpc::health::v1::HealthCheckResponse response;
  ASSERT_TRUE(health->Check(&ctx, request, &response).ok());
  EXPECT_EQ(response.status(), grpc::health::v1::HealthCheckResponse::SERVING);
  grpc::ClientContext named_ctx;
  request.set_service("lsqsurf.v1.Reconstruction");
  ASSERT_TRUE(health->Check(&named_ctx, request, &response).ok());
  EXPECT_EQ(response.status(), grpc::health::v1::HealthCheckResponse::SERVING);

  // The same through the CLI, as a container's HEALTHCHECK runs it.
  const ClientRun serving = Client(server.address(), "health");
  EXPECT_EQ(serving.code, 0) << serving.output;
  EXPECT_EQ(Trim(serving.output), "SERVING");
  EXPECT_EQ(Client(server.address(), "health --service lsqsurf.v1.Reconstruction").code, 0);
  const ClientRun unknown = Client(server.address(), "health --service no.such.Service");
  EXPECT_NE(unknown.code, 0);
  EXPECT_NE(unknown.output.find("health:"), std::string::npos) << unknown.output;
  const std::string address = server.address();
  server.Kill(SIGKILL);
  const ClientRun gone = Client(address, "health --timeout 1");
  EXPECT_NE(gone.code, 0) << gone.output;
}

// The PU result carries the depth and degree of the fit that made each region, through Draco
// (the transfer format) into the PLY the client writes.
TEST_F(EndToEnd, PuMeshCarriesDepthAndDegreeToThePly) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const std::string in = WriteCloud("sphere.ply", testing::SphereCloud(8000));
  const std::string out = (dir_ / "pu.ply").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out + " --method pu");
  ASSERT_EQ(r.code, 0) << r.output;
  auto mesh = io::ReadMeshFile(out);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(core::AnalyzeTopology(*mesh).watertight());
  for (const auto& v : mesh->vertices) EXPECT_NEAR(v.norm(), 1.0f, 0.002f);
  std::map<std::string, std::pair<float, float>> ranges;
  for (const auto& a : mesh->vertex_attributes) {
    ASSERT_EQ(a.values.size(), mesh->vertices.size()) << a.name;
    ranges[a.name] = {*std::min_element(a.values.begin(), a.values.end()),
                      *std::max_element(a.values.begin(), a.values.end())};
  }
  ASSERT_TRUE(ranges.contains("depth") && ranges.contains("degree"));
  EXPECT_GE(ranges["depth"].first, 1.0f);
  EXPECT_LE(ranges["depth"].second, 18.0f);
  EXPECT_GE(ranges["degree"].first, 0.0f);
  EXPECT_LE(ranges["degree"].second, 5.0f);
}

// The mesh written to `path` is one closed piece, welded by position, enclosing `volume`.
void ExpectOneClosedSolid(const std::string& path, double volume, double tolerance) {
  auto mesh = io::ReadMeshFile(path);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  const core::MeshTopology topology = core::AnalyzeTopology(core::WeldByPosition(*mesh));
  EXPECT_TRUE(topology.watertight());
  EXPECT_EQ(topology.components, 1);
  EXPECT_NEAR(core::EnclosedVolume(*mesh), volume, tolerance);
}

// The share of the mesh's area whose faces (by their winding) face at least one of `eyes`.
double AreaFacing(const core::TriangleMesh& mesh, const std::vector<core::Vec3d>& eyes) {
  double facing = 0, total = 0;
  for (const core::Triangle& t : mesh.faces) {
    const core::Vec3d a = mesh.vertices[t[0]].cast<double>(), b = mesh.vertices[t[1]].cast<double>(),
                      c = mesh.vertices[t[2]].cast<double>();
    const core::Vec3d normal = (b - a).cross(c - a), centre = (a + b + c) / 3;
    total += normal.norm();
    if (std::any_of(eyes.begin(), eyes.end(), [&](const core::Vec3d& e) { return normal.dot(e - centre) > 0; })) {
      facing += normal.norm();
    }
  }
  return total > 0 ? facing / total : 0;
}

// A single view written as PCL writes one, with the camera's position in its VIEWPOINT and no
// normals: the client passes the position on, and the surface faces the camera.
TEST_F(EndToEnd, APcdViewsViewpointTurnsItsSurfaceTowardTheCamera) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const core::Vec3d eye(0, -2.5, 1.6);
  core::PointCloud view = testing::BallOnATableView(eye);
  view.normals.clear();
  const std::string in = (dir_ / "view.pcd").string();
  ASSERT_TRUE(io::WriteFileAtomically(
                  in, io::EncodePcd(view, io::PcdEncoding::kBinaryCompressed, {eye.x(), eye.y(), eye.z(), 1, 0, 0, 0}))
                  .ok());
  const std::string out = (dir_ / "view.ply").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out + " --stats");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("normals_toward_viewpoint = 1"), std::string::npos) << r.output;
  auto mesh = io::ReadMeshFile(out);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_GT(AreaFacing(*mesh, {eye}), 0.99);
  // An empty viewpoint says the file's is not to be used.
  const ClientRun unset = Client(server.address(), "reconstruct " + in + " -o " + out + " --stats --param viewpoint=");
  ASSERT_EQ(unset.code, 0) << unset.output;
  EXPECT_EQ(unset.output.find("normals_toward_viewpoint"), std::string::npos) << unset.output;
}

// A stereo-like view whose depths lie on disparity steps, each terrace of the table many pixels
// deep: undone by default, the surface faces the camera and comes back in one piece; left as
// they are, the same points give terraces square to the optical axis, in pieces.
TEST_F(EndToEnd, AViewsDepthStepsAreUndone) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const core::Vec3d eye(0, -2.5, 1.6);
  core::PointCloud view = testing::BallOnATableView(eye, {.scale = 2, .step = 0.024});
  view.normals.clear();
  const std::string in = (dir_ / "stepped.pcd").string();
  ASSERT_TRUE(io::WriteFileAtomically(
                  in, io::EncodePcd(view, io::PcdEncoding::kBinaryCompressed, {eye.x(), eye.y(), eye.z(), 1, 0, 0, 0}))
                  .ok());
  struct Surface {
    double facing = 0, distance = 0;  // Mean of the vertices' to the ball or the table.
    int64_t components = 0;
  };
  auto reconstruct = [&](const std::string& extra, bool undone) {
    const std::string out = (dir_ / "stepped.ply").string();
    const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out + " --method pu --stats" + extra);
    EXPECT_EQ(r.code, 0) << r.output;
    EXPECT_EQ(r.output.find("depth_step = ") != std::string::npos, undone) << r.output;
    EXPECT_EQ(r.output.find("were moved along their rays") != std::string::npos, undone) << r.output;
    auto mesh = io::ReadMeshFile(out);
    EXPECT_TRUE(mesh.ok()) << mesh.status();
    if (!mesh.ok()) return Surface{};
    double distance = 0;
    for (const core::Vec3f& v : mesh->vertices) {
      const core::Vec3d p = v.cast<double>();
      distance += std::min(std::abs((p - core::Vec3d(0, 0, 0.3)).norm() - 0.3), std::abs(p.z()));
    }
    return Surface{AreaFacing(*mesh, {eye}), distance / static_cast<double>(mesh->vertices.size()),
                   core::AnalyzeTopology(core::WeldByPosition(*mesh)).components};
  };
  const Surface undone = reconstruct("", true), stepped = reconstruct(" --param undo_depth_steps=false", false);
  std::printf(
      "  facing the camera %.4f (steps left: %.4f), distance to the truth %.2e (%.2e), components %lld (%lld)\n",
      undone.facing, stepped.facing, undone.distance, stepped.distance, static_cast<long long>(undone.components),
      static_cast<long long>(stepped.components));
  EXPECT_GT(undone.facing, 0.95);
  EXPECT_LE(undone.components, 2);
  EXPECT_GE(stepped.components, 5);
  EXPECT_LT(undone.distance, 0.5 * stepped.distance);
}

// A ball scanned all round, in a PCD that names one camera beside it, as a tool that knows no
// better writes it: that position hides the far half behind the near one, so the server sets it
// aside (the client says why) and orients by propagation; the ball comes back closed and
// outward. Turned toward the camera, the far half would face inward.
TEST_F(EndToEnd, APcdViewpointThatHidesItsPointsIsSetAside) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  core::PointCloud ball = testing::SphereCloud(20'000);
  ball.normals.clear();
  const std::string in = (dir_ / "ball.pcd").string();
  ASSERT_TRUE(io::WriteFileAtomically(in, io::EncodePcd(ball, io::PcdEncoding::kBinary, {0, -3, 0, 1, 0, 0, 0})).ok());
  const std::string out = (dir_ / "ball.ply").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out + " --method pu --stats");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("normals were oriented by propagation instead"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("normals_toward_viewpoint = 0"), std::string::npos) << r.output;
  const size_t share = r.output.find("viewpoint_hidden_share = ");
  ASSERT_NE(share, std::string::npos) << r.output;
  EXPECT_GT(std::stod(r.output.substr(share + 25)), 0.4) << r.output;
  ExpectOneClosedSolid(out, 4 * std::numbers::pi / 3, 0.02);
}

// Two stations of a terrestrial scanner exported as PTX: the client passes both positions on,
// each point's normal faces its own scanner, and the surface faces one of them everywhere.
TEST_F(EndToEnd, APtxFilesStationsEachTurnTheirOwnPointsTowardThem) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const core::Vec3d eyes[2] = {core::Vec3d(0, -2.5, 1.6), core::Vec3d(0.4, 2.6, 1.4)};
  core::PointCloud views[2] = {testing::BallOnATableView(eyes[0]), testing::BallOnATableView(eyes[1])};
  for (core::PointCloud& v : views) v.normals.clear();
  const std::string in = (dir_ / "stations.ptx").string();
  ASSERT_TRUE(io::WriteFileAtomically(in, io::EncodePtx({{eyes[0], &views[0]}, {eyes[1], &views[1]}})).ok());
  const std::string out = (dir_ / "stations.ply").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out + " --stats");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("normals_toward_viewpoint = 2"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("holds 2 scans"), std::string::npos) << r.output;
  auto mesh = io::ReadMeshFile(out);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_GT(AreaFacing(*mesh, {eyes[0], eyes[1]}), 0.99);
}

// A coloured scan keeps its colour: every method's mesh carries red, green and blue, written as
// viewers read them (uchar PLY properties, OBJ vertex colours), within a few levels of the colour
// at the vertex's place.
TEST_F(EndToEnd, AColouredCloudsMeshKeepsItsColours) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  core::PointCloud cloud = testing::SphereCloud(20000);
  auto colour_at = [](const core::Vec3f& p) {  // A smooth colour field over the sphere.
    return core::Vec3f(127.5f * (1 + p.x()), 127.5f * (1 + p.y()), 127.5f * (1 + p.z() * p.z()) - 1);
  };
  for (const char* channel : {"red", "green", "blue"}) cloud.attributes.push_back({channel, {}});
  for (const core::Vec3f& p : cloud.positions) {
    for (int c = 0; c < 3; ++c) cloud.attributes[static_cast<size_t>(c)].values.push_back(std::round(colour_at(p)[c]));
  }
  const std::string in = WriteCloud("coloured.ply", cloud);
  for (const std::string method : {"iamls", "pu"}) {
    const std::string ply = (dir_ / (method + ".ply")).string(), obj = (dir_ / (method + ".obj")).string();
    const ClientRun r =
        Client(server.address(), "reconstruct " + in + " -o " + ply + " -o " + obj + " --stats --method " + method);
    ASSERT_EQ(r.code, 0) << r.output;
    EXPECT_NE(r.output.find("carried_attributes = 3"), std::string::npos) << r.output;
    auto bytes = io::ReadFileBytes(ply);
    ASSERT_TRUE(bytes.ok());
    EXPECT_NE(bytes->find("property uchar red\nproperty uchar green\nproperty uchar blue\n"), std::string::npos);
    for (const std::string& path : {ply, obj}) {
      auto mesh = io::ReadMeshFile(path);
      ASSERT_TRUE(mesh.ok()) << mesh.status();
      std::vector<const core::ScalarAttribute*> rgb;
      for (const auto& a : mesh->vertex_attributes) {
        if (a.name == "red" || a.name == "green" || a.name == "blue") rgb.push_back(&a);
      }
      ASSERT_EQ(rgb.size(), 3u) << path;
      double worst = 0;
      for (size_t v = 0; v < mesh->vertices.size(); ++v) {
        const core::Vec3f expected = colour_at(mesh->vertices[v].normalized());
        for (int c = 0; c < 3; ++c)
          worst = std::max<double>(worst, std::abs(rgb[static_cast<size_t>(c)]->values[v] - expected[c]));
      }
      EXPECT_LT(worst, 4.0) << path;
    }
  }
}

// A cloud larger than a part goes up in parts; a PU job over tile_points then streams it and
// delivers its mesh in parts, which the client joins into one file as they come.
TEST_F(EndToEnd, ACloudSentInPartsComesBackAsOneClosedMesh) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const std::string in = WriteCloud("block.ply", testing::DrilledBlockCloud(12'000, 2.0, 0.6, 0.3, 0.3));
  const std::string out = (dir_ / "block-out.ply").string(), again = (dir_ / "block-again.obj").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + out +
                                                   " --method pu --part-points 2500 --param tile_points=3000 "
                                                   "--param support_cap=16 --stats");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("input_streamed = 1"), std::string::npos) << r.output;
  auto mesh = io::ReadMeshFile(out);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  const core::MeshTopology topology = core::AnalyzeTopology(core::WeldByPosition(*mesh));
  EXPECT_TRUE(topology.watertight());
  EXPECT_EQ(topology.euler_characteristic(), 0);
  EXPECT_NEAR(core::EnclosedVolume(*mesh), 8 * 2.0 * 0.6 * 0.3 - M_PI * 0.3 * 0.3 * 2 * 0.3, 0.02);  // Box less hole.
  bool has_degree = false;
  for (const auto& a : mesh->vertex_attributes) has_degree |= a.name == "degree";
  EXPECT_TRUE(has_degree);
  // `lsqsurf fetch` joins the parts the same way.
  const std::string id = r.output.substr(r.output.find("job ") + 4, 32);
  const ClientRun fetched = Client(server.address(), "fetch " + id + " -o " + again);
  ASSERT_EQ(fetched.code, 0) << fetched.output;
  auto obj = io::ReadMeshFile(again);
  ASSERT_TRUE(obj.ok()) << obj.status();
  EXPECT_EQ(obj->faces.size(), mesh->faces.size());

  // Into a directory: one Draco mesh per tile, each whole on its own; together the same closed mesh.
  const std::string tiles = (dir_ / "tiles").string() + "/";
  const ClientRun tiled = Client(server.address(), "fetch " + id + " -o " + tiles);
  ASSERT_EQ(tiled.code, 0) << tiled.output;
  core::TriangleMesh joined;
  size_t files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(tiles)) {
    ++files;
    EXPECT_EQ(entry.path().extension(), ".drc");
    auto tile = io::ReadMeshFile(entry.path().string());
    ASSERT_TRUE(tile.ok()) << tile.status();
    const auto offset = static_cast<uint32_t>(joined.vertices.size());
    joined.vertices.insert(joined.vertices.end(), tile->vertices.begin(), tile->vertices.end());
    for (const core::Triangle& f : tile->faces) joined.faces.push_back({f[0] + offset, f[1] + offset, f[2] + offset});
  }
  EXPECT_NE(tiled.output.find("wrote " + std::to_string(files) + " tiles"), std::string::npos) << tiled.output;
  EXPECT_GE(files, 4u);
  EXPECT_EQ(joined.faces.size(), mesh->faces.size());
  EXPECT_TRUE(core::AnalyzeTopology(core::WeldByPosition(joined)).watertight());
  const ClientRun not_parts = Client(server.address(), "fetch " + id + " --name stats.csv -o " + tiles);
  EXPECT_NE(not_parts.code, 0);

  // Its picture is drawn from the parts.
  if (LSQSURF_WITH_EGL) {
    const std::string picture = (dir_ / "block.png").string();
    const ClientRun drawn = Client(server.address(), "render " + id + " -o " + picture + " --size 128");
    ASSERT_EQ(drawn.code, 0) << drawn.output;
    int w = 0, h = 0, channels = 0;
    unsigned char* pixels = stbi_load(picture.c_str(), &w, &h, &channels, 4);
    ASSERT_NE(pixels, nullptr) << stbi_failure_reason();
    EXPECT_EQ(w, 128);
    EXPECT_LT(pixels[4 * (64 * 128 + 64)], 250);  // The block in the middle.
    stbi_image_free(pixels);
  }
}

// A PU job keeps its function; `lsqsurf csg` halves it with a plane by reference and `lsqsurf
// edit` changes it in a ball.
TEST_F(EndToEnd, CsgAndEditOfAKeptPuResultThroughTheCli) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const std::string in = WriteCloud("sphere.ply", testing::SphereCloud(8000));
  const ClientRun submitted = Client(server.address(), "submit " + in + " --method pu");
  ASSERT_EQ(submitted.code, 0) << submitted.output;
  const std::string id = Trim(submitted.output);
  ASSERT_EQ(Client(server.address(), "watch " + id).code, 0);
  const std::string out = (dir_ / "half.ply").string();
  const ClientRun r = Client(server.address(), "csg 'intersection(job:" + id + ", plane(p=0,0,0 n=0,0,1))' -o " + out);
  ASSERT_EQ(r.code, 0) << r.output;
  ExpectOneClosedSolid(out, 2 * std::numbers::pi / 3, 0.02);
  const ClientRun bad = Client(server.address(), "csg 'union(job:" + id + ")' -o " + out);
  EXPECT_EQ(bad.code, 1) << bad.output;
  EXPECT_NE(bad.output.find("at least 2 operands"), std::string::npos) << bad.output;

  // A local edit of the same kept function: planar fits in a ball, still one closed surface.
  const std::string edited = (dir_ / "edited.ply").string();
  const ClientRun e = Client(server.address(), "edit " + id + " --ball 1,0,0,0.3 --set degree=1 -o " + edited);
  ASSERT_EQ(e.code, 0) << e.output;
  auto edited_mesh = io::ReadMeshFile(edited);
  ASSERT_TRUE(edited_mesh.ok()) << edited_mesh.status();
  EXPECT_TRUE(core::AnalyzeTopology(core::WeldByPosition(*edited_mesh)).watertight());
  const ClientRun two =
      Client(server.address(), "edit " + id + " --ball 1,0,0,0.3 --set degree=1 --remove -o " + edited);
  EXPECT_EQ(two.code, 3) << two.output;
  EXPECT_NE(two.output.find("give one of"), std::string::npos) << two.output;
}

// Pictures: a preview written by reconstruct, an on-demand render coloured by the PU degree,
// and the status codes of bad render requests.
TEST_F(EndToEnd, RendersResultsThroughTheCliAndTheApi) {
  if (!LSQSURF_WITH_EGL) GTEST_SKIP() << "built without EGL: the server draws no pictures";
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const std::string in = WriteCloud("sphere.ply", testing::SphereCloud(8000));
  const std::string preview = (dir_ / "preview.png").string();
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + (dir_ / "pu.drc").string() +
                                                   " --method pu --preview " + preview);
  ASSERT_EQ(r.code, 0) << r.output;
  auto decode = [](const std::string& path, int* w, int* h) {
    int channels = 0;
    return stbi_load(path.c_str(), w, h, &channels, 4);
  };
  int w = 0, h = 0;
  unsigned char* pixels = decode(preview, &w, &h);
  ASSERT_NE(pixels, nullptr) << stbi_failure_reason();
  EXPECT_EQ(w, 1024);
  EXPECT_EQ(h, 1024);
  auto pixel = [&](int x, int y) {
    return pixels + 4 * (static_cast<size_t>(y) * static_cast<size_t>(w) + static_cast<size_t>(x));
  };
  EXPECT_EQ(pixel(2, 2)[0], 255);          // White background in the corner,
  EXPECT_LT(pixel(512, 512)[0] + 0, 250);  // the shaded sphere in the middle.
  stbi_image_free(pixels);

  const size_t at = r.output.find("job ");
  ASSERT_NE(at, std::string::npos) << r.output;
  const std::string id = r.output.substr(at + 4, r.output.find_first_of(" \n:", at + 4) - (at + 4));
  ASSERT_EQ(id.size(), 32u) << r.output;
  const std::string view = (dir_ / "degree.png").string();
  const ClientRun coloured = Client(server.address(), "render " + id + " -o " + view + " --color degree --size 256");
  ASSERT_EQ(coloured.code, 0) << coloured.output;
  EXPECT_NE(coloured.output.find("degree from"), std::string::npos) << coloured.output;
  pixels = decode(view, &w, &h);
  ASSERT_NE(pixels, nullptr);
  EXPECT_EQ(w, 256);
  stbi_image_free(pixels);

  auto stub = v1::Reconstruction::NewStub(grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials()));
  auto render = [&](v1::RenderRequest request) {
    grpc::ClientContext ctx;
    v1::RenderResponse response;
    return stub->Render(&ctx, request, &response);
  };
  v1::RenderRequest request;
  request.set_job_id("0123456789abcdef");
  EXPECT_EQ(render(request).error_code(), grpc::StatusCode::NOT_FOUND);
  request.set_job_id(id);
  request.mutable_options()->set_width(100000);
  EXPECT_EQ(render(request).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  request.mutable_options()->set_width(64);
  request.mutable_options()->set_up_axis(static_cast<v1::RenderOptions::UpAxis>(7));  // Not in the enum.
  const grpc::Status bad_axis = render(request);
  EXPECT_EQ(bad_axis.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(bad_axis.error_message().find("up_axis"), std::string::npos) << bad_axis.error_message();
  request.mutable_options()->set_up_axis(v1::RenderOptions::UP_AXIS_Y);
  request.mutable_options()->set_color("nope");
  const grpc::Status unknown = render(request);
  EXPECT_EQ(unknown.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(unknown.error_message().find("degree"), std::string::npos) << unknown.error_message();
  request.mutable_options()->set_color("");
  request.set_name("no-such-artifact.drc");
  EXPECT_EQ(render(request).error_code(), grpc::StatusCode::NOT_FOUND);
}

// A job that draws its own preview: asked for at submission, checked there, fetched as a PNG.
TEST_F(EndToEnd, JobsDrawTheirOwnPreview) {
  if (!LSQSURF_WITH_EGL) GTEST_SKIP() << "built without EGL: the server draws no pictures";
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const std::string in = WriteCloud("sphere.ply", testing::SphereCloud(8000));
  const ClientRun bad = Client(server.address(), "submit " + in + " --method iamls --job-preview --color degree");
  EXPECT_EQ(bad.code, 1);
  EXPECT_NE(bad.output.find("no attribute 'degree'"), std::string::npos) << bad.output;
  const ClientRun submitted =
      Client(server.address(), "submit " + in + " --method pu --job-preview --color degree --size 160 --transparent");
  ASSERT_EQ(submitted.code, 0) << submitted.output;
  const std::string id = Trim(submitted.output);
  ASSERT_EQ(Client(server.address(), "watch " + id).code, 0);
  const ClientRun status = Client(server.address(), "status " + id);
  EXPECT_NE(status.output.find("result     preview.png"), std::string::npos) << status.output;
  const std::string png = (dir_ / "job-preview.png").string();
  ASSERT_EQ(Client(server.address(), "fetch " + id + " --name preview.png -o " + png).code, 0);
  int w = 0, h = 0, channels = 0;
  unsigned char* pixels = stbi_load(png.c_str(), &w, &h, &channels, 4);
  ASSERT_NE(pixels, nullptr) << stbi_failure_reason();
  EXPECT_EQ(w, 160);
  EXPECT_EQ(h, 160);
  EXPECT_EQ(pixels[3], 0);                          // Transparent corner,
  EXPECT_EQ(pixels[4 * (80 * 160 + 80) + 3], 255);  // the sphere in the middle.
  stbi_image_free(pixels);
}

// Track pictures are framed on the unit cube: seen from above, the sphere circles the image
// centre by the rotation's angle per output frame; a turntable camera adds its own turn.
TEST_F(EndToEnd, TrackFramesArePicturesOfAFixedScene) {
  if (!LSQSURF_WITH_EGL) GTEST_SKIP() << "built without EGL: the server draws no pictures";
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  // Angles, seen in the picture, of the sphere's centroid about the image centre, per frame.
  auto angles = [&](const std::string& extra) {
    const fs::path out = dir_ / ("pictures" + std::to_string(extra.size()));
    const ClientRun r = Client(server.address(),
                               "track --interface sphere --field rotation --h 0.03125 --dt 10 "
                               "--steps 16 --stride 8 --pictures --size 128 --transparent "
                               "--elevation 89 " +
                                   extra + " -o " + out.string());
    EXPECT_EQ(r.code, 0) << r.output;
    std::vector<double> result;
    for (int step : {0, 8, 16}) {
      char name[32];
      std::snprintf(name, sizeof(name), "frame_%05d.png", step);
      int w = 0, h = 0, channels = 0;
      unsigned char* pixels = stbi_load((out / name).string().c_str(), &w, &h, &channels, 4);
      EXPECT_NE(pixels, nullptr) << name;
      if (pixels == nullptr) return result;
      double n = 0, sx = 0, sy = 0;
      for (int y = 0; y < h; ++y) {
        for (int x = 0; x < w; ++x) {
          if (pixels[4 * (y * w + x) + 3] < 128) continue;
          n += 1, sx += x + 0.5, sy += y + 0.5;
        }
      }
      stbi_image_free(pixels);
      EXPECT_GT(n, 50) << name;
      result.push_back(std::atan2(sy / n - 64, sx / n - 64) * 180 / M_PI);
    }
    return result;
  };
  auto turn = [](double from, double to) { return std::remainder(to - from, 360.0); };
  const double per_frame = 360.0 * 80 / 628;  // Zalesak's field turns once in 628 time units.
  const std::vector<double> fixed = angles("");
  ASSERT_EQ(fixed.size(), 3u);
  EXPECT_NEAR(std::abs(turn(fixed[0], fixed[1])), per_frame, 3);
  EXPECT_NEAR(std::abs(turn(fixed[1], fixed[2])), per_frame, 3);
  const std::vector<double> turning = angles("--turntable 30");
  ASSERT_EQ(turning.size(), 3u);
  EXPECT_NEAR(std::abs(std::abs(turn(turning[0], turning[1])) - per_frame), 30, 3);
  EXPECT_NEAR(turn(fixed[0], turning[0]), 0, 1);  // The first frame is the same view.
}

TEST_F(EndToEnd, BadInputsGetClearErrorsAndTheServerKeepsServing) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  core::PointCloud nan_cloud = testing::SphereCloud(500);
  nan_cloud.positions[3].x() = std::numeric_limits<float>::infinity();
  core::PointCloud bare = testing::SphereCloud(500);
  bare.normals.clear();
  const std::string good = WriteCloud("good.ply", testing::SphereCloud(3000));
  // Quantized Draco cannot carry NaN, but a lossless upload can: the server must catch it.
  io::WriteOptions lossless;
  lossless.draco.position_bits = 0;
  const std::string lossless_nan = (dir_ / "nan.drc").string();
  ASSERT_TRUE(io::WritePointCloudFile(lossless_nan, nan_cloud, lossless).ok());
  // A truncated Draco upload: the client sends .drc files as they are.
  ASSERT_TRUE(io::WritePointCloudFile((dir_ / "full.drc").string(), testing::SphereCloud(3000)).ok());
  const std::string full = *io::ReadFileBytes((dir_ / "full.drc").string());
  ASSERT_TRUE(io::WriteFileAtomically((dir_ / "cut.drc").string(), full.substr(0, full.size() / 2)).ok());
  struct Case {
    std::string args;
    int code;
    std::string fragment;
  } cases[] = {
      {"reconstruct " + lossless_nan + " -o x.ply", 1, "NaN or infinite"},                      // Server-side check.
      {"reconstruct " + WriteCloud("nan.ply", nan_cloud) + " -o x.ply", 3, "NaN or infinite"},  // Client-side.
      {"reconstruct " + (dir_ / "cut.drc").string() + " -o x.ply", 1, "Draco"},
      // Client-side: the proto names every method and parameter; ranges are the server's.
      {"reconstruct " + good + " -o x.ply --method nosuch", 3, "unknown method"},
      {"reconstruct " + good + " -o x.ply --param epsilon=7", 1, "out of range"},
      {"reconstruct " + good + " -o x.ply --param colour=1", 3, "unknown parameter"},
      {"reconstruct " + WriteCloud("bare.ply", bare) + " -o x.ply --param estimate_normals=0", 1, "no normals"},
      {"reconstruct " + (dir_ / "missing.ply").string() + " -o x.ply", 3, "no such file"},
      {"status 0123456789abcdef", 1, "no job"},
  };
  for (const auto& c : cases) {
    const ClientRun r = Client(server.address(), c.args);
    EXPECT_EQ(r.code, c.code) << c.args << "\n" << r.output;
    EXPECT_NE(r.output.find(c.fragment), std::string::npos) << c.args << "\n" << r.output;
  }
  const ClientRun ok = Client(server.address(), "reconstruct " + good + " -o " + (dir_ / "ok.ply").string());
  EXPECT_EQ(ok.code, 0) << ok.output;
}

// A legacy VTK volume through the CLI: isosurface with a colour field, a job kept for probes,
// probes at points of an XYZ file, and a broken file refused before anything is sent.
TEST_F(EndToEnd, VolumeIsosurfaceAndProbesThroughTheCli) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const volume::AnalyticField franke = volume::Franke3d();
  volume::VolumeMesh mesh = volume::JitteredTetMesh(franke.domain, 11, 0.3, 4);
  volume::SampleField(mesh, franke);
  volume::SampleField(mesh, {"height", [](const core::Vec3d& x) { return x.z(); }, nullptr, franke.domain});
  const std::string vtk = (dir_ / "flow.vtk").string();
  ASSERT_TRUE(io::WriteFileAtomically(vtk, io::EncodeLegacyVtk(mesh, true)).ok());

  const std::string iso = (dir_ / "iso.ply").string();
  const ClientRun r =
      Client(server.address(), "volume " + vtk + " --field franke --iso 0.35 --color-by height -o " + iso);
  ASSERT_EQ(r.code, 0) << r.output;
  auto surface = io::ReadMeshFile(iso);
  ASSERT_TRUE(surface.ok()) << surface.status();
  ASSERT_FALSE(surface->faces.empty());
  ASSERT_EQ(surface->vertex_attributes.size(), 1u);
  EXPECT_EQ(surface->vertex_attributes[0].name, "height");
  for (size_t v = 0; v < surface->vertices.size(); ++v) {  // The colour field is z itself.
    EXPECT_NEAR(surface->vertex_attributes[0].values[v], surface->vertices[v].z(), 2e-3);
  }

  const ClientRun submitted = Client(server.address(), "-q submit " + vtk + " --method volume --field franke");
  ASSERT_EQ(submitted.code, 0) << submitted.output;
  const std::string id = Trim(submitted.output);
  EXPECT_EQ(id.find_first_of(" \n"), std::string::npos) << id;  // The id alone.
  ASSERT_EQ(Client(server.address(), "-q watch " + id).code, 0);
  const std::string points = (dir_ / "points.xyz").string();
  ASSERT_TRUE(io::WriteFileAtomically(points, "0.5 0.5 0.5\n0.25 0.7 0.4\n3 3 3\n").ok());
  const std::string csv = (dir_ / "values.csv").string();
  const ClientRun probed = Client(server.address(), "-q probe " + id + " " + points + " -o " + csv);
  ASSERT_EQ(probed.code, 0) << probed.output;
  auto table = io::ReadFileBytes(csv);
  ASSERT_TRUE(table.ok());
  std::istringstream rows(*table);
  std::string line;
  std::getline(rows, line);
  EXPECT_EQ(line, "x,y,z,value,gx,gy,gz");
  std::getline(rows, line);
  EXPECT_TRUE(line.starts_with("0.5,0.5,0.5,")) << line;
  EXPECT_NEAR(std::stod(line.substr(12, line.find(',', 12) - 12)), franke.value({0.5, 0.5, 0.5}), 0.01) << line;
  std::getline(rows, line);
  EXPECT_TRUE(line.starts_with("0.25,0.7,0.4,")) << line;
  std::getline(rows, line);
  EXPECT_EQ(line, "3,3,3,,,,");

  // A cell in the mirrored order and a value missing, as some writers leave them: the client fills
  // the value in from the neighbours (NaN cannot travel quantized), the server turns the cell.
  volume::VolumeMesh untidy = mesh;
  std::swap(untidy.cell_vertices[0], untidy.cell_vertices[1]);
  untidy.fields[0].values[200] = std::nanf("");
  const std::string untidy_vtk = (dir_ / "untidy.vtk").string();
  ASSERT_TRUE(io::WriteFileAtomically(untidy_vtk, io::EncodeLegacyVtk(untidy, false)).ok());
  const ClientRun taken = Client(server.address(), "volume " + untidy_vtk + " --field franke --iso 0.3 -o " + iso);
  ASSERT_EQ(taken.code, 0) << taken.output;
  EXPECT_NE(taken.output.find("1 vertices without a value were filled in"), std::string::npos) << taken.output;
  EXPECT_NE(taken.output.find("reoriented_cells"), std::string::npos) << taken.output;

  // Values missing at most vertices have no reading: refused before anything is sent.
  volume::VolumeMesh empty = mesh;
  for (float& v : empty.fields[0].values) v = std::nanf("");
  const std::string bad = (dir_ / "no-values.vtk").string();
  ASSERT_TRUE(io::WriteFileAtomically(bad, io::EncodeLegacyVtk(empty, false)).ok());
  const ClientRun refused = Client(server.address(), "volume " + bad + " --field franke --iso 0.3 -o " + iso);
  EXPECT_EQ(refused.code, 3) << refused.output;
  EXPECT_NE(refused.output.find("field 'franke' is NaN or infinite at 1331 of 1331 vertices"), std::string::npos)
      << refused.output;
}

TEST_F(EndToEnd, CancelAndFullQueue) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data", {"--workers", "1", "--max-queue", "1"}));
  const std::string id = SubmitLongJob(server.address());
  ASSERT_TRUE(WaitRunning(server.address(), id));
  const std::string cloud = WriteCloud("cloud.ply", testing::SphereCloud(3000));
  const ClientRun second = Client(server.address(), "submit " + cloud);
  ASSERT_EQ(second.code, 0) << second.output;
  const ClientRun third = Client(server.address(), "submit " + cloud);
  EXPECT_EQ(third.code, 1);
  EXPECT_NE(third.output.find("queue is full"), std::string::npos) << third.output;

  EXPECT_EQ(Client(server.address(), "cancel " + id).code, 0);
  const ClientRun watched = Client(server.address(), "watch " + id);
  EXPECT_EQ(watched.code, 2) << watched.output;
  EXPECT_NE(watched.output.find("cancelled"), std::string::npos);
  EXPECT_EQ(Client(server.address(), "cancel " + Trim(second.output)).code, 0);
  const ClientRun list = Client(server.address(), "list");
  EXPECT_NE(list.output.find("cancelled"), std::string::npos) << list.output;
}

// The API itself, without the client: malformed streams and unknown ids get the documented codes.
TEST_F(EndToEnd, RawApiStatusCodes) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  auto stub = v1::Reconstruction::NewStub(grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials()));
  auto submit = [&](const std::vector<v1::SubmitJobRequest>& messages) {
    grpc::ClientContext ctx;
    v1::Job job;
    auto writer = stub->SubmitJob(&ctx, &job);
    for (const auto& m : messages) writer->Write(m);
    writer->WritesDone();
    return writer->Finish();
  };
  v1::SubmitJobRequest spec, chunk, huge;
  spec.mutable_spec()->mutable_iamls();
  chunk.set_input_chunk("abc");
  huge.set_input_chunk(std::string((1 << 20) + 1, 'x'));
  EXPECT_EQ(submit({chunk}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);        // No spec first.
  EXPECT_EQ(submit({spec, spec}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);   // Two specs.
  EXPECT_EQ(submit({spec, huge}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);   // Chunk > 1 MiB.
  EXPECT_EQ(submit({spec}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);         // No input.
  EXPECT_EQ(submit({spec, chunk}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);  // Not Draco.
  // A text that is not an id is refused as such (not looked up, logged or echoed); a missing id
  // is not found.
  const std::string missing(32, '7');
  for (const auto& [id, code] : {std::pair{std::string("nope"), grpc::StatusCode::INVALID_ARGUMENT},
                                 std::pair{std::string(1 << 20, 'a'), grpc::StatusCode::INVALID_ARGUMENT},
                                 std::pair{missing, grpc::StatusCode::NOT_FOUND}}) {
    grpc::ClientContext ctx;
    v1::GetJobRequest request;
    request.set_job_id(id);
    v1::Job job;
    const grpc::Status status = stub->GetJob(&ctx, request, &job);
    EXPECT_EQ(status.error_code(), code);
    EXPECT_LE(status.error_message().size(), 1024u);
  }
  // Reads a server stream to its end and returns its status.
  auto drain = [](auto reader, auto message) {
    while (reader->Read(&message)) {
    }
    return reader->Finish().error_code();
  };
  {
    grpc::ClientContext ctx;
    v1::FetchResultRequest request;
    request.set_job_id(missing);
    EXPECT_EQ(drain(stub->FetchResult(&ctx, request), v1::ResultChunk()), grpc::StatusCode::NOT_FOUND);
  }
  {
    grpc::ClientContext ctx;
    v1::WatchJobRequest request;
    request.set_job_id(missing);
    EXPECT_EQ(drain(stub->WatchJob(&ctx, request), v1::JobEvent()), grpc::StatusCode::NOT_FOUND);
  }
  // A running job cannot be deleted, and its result cannot be fetched yet.
  const std::string id = SubmitLongJob(server.address());
  ASSERT_TRUE(WaitRunning(server.address(), id));
  {
    grpc::ClientContext ctx;
    v1::DeleteJobRequest request;
    request.set_job_id(id);
    v1::DeleteJobResponse response;
    EXPECT_EQ(stub->DeleteJob(&ctx, request, &response).error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  }
  {
    grpc::ClientContext ctx;
    v1::ListMethodsResponse response;
    ASSERT_TRUE(stub->ListMethods(&ctx, {}, &response).ok());
    const std::vector<std::string> expected = {"iamls", "pu",   "ramls", "apss",   "aamls", "imls",
                                               "csg",   "edit", "track", "volume", "probe"};
    ASSERT_EQ(response.methods_size(), static_cast<int>(expected.size()));
    for (size_t i = 0; i < expected.size(); ++i) EXPECT_EQ(response.methods(static_cast<int>(i)).name(), expected[i]);
  }
  EXPECT_EQ(Client(server.address(), "cancel " + id).code, 0);
}

// `lsqsurf track`: a named sphere through a quarter of Zalesak's rotation, then an uploaded
// interface. Frames decode with normals and as many points as stats.csv says; the volume holds.
TEST_F(EndToEnd, TrackWritesFramesAndStatistics) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  const fs::path out = dir_ / "frames";
  const ClientRun r = Client(server.address(),
                             "track --interface sphere --field rotation --h 0.03125 --dt 10 "
                             "--steps 16 --stride 8 --meshes -o " +
                                 out.string());
  ASSERT_EQ(r.code, 0) << r.output;
  auto csv = io::ReadFileBytes((out / "stats.csv").string());
  ASSERT_TRUE(csv.ok());
  std::istringstream lines(*csv);
  std::string line;
  std::getline(lines, line);
  EXPECT_EQ(line, "step,time,points,volume,volume_change,mesh_volume");
  int rows = 0;
  while (std::getline(lines, line)) {
    int step = 0;
    double time = 0, volume = 0, change = 0, mesh_volume = 0;
    size_t points = 0;
    ASSERT_EQ(
        std::sscanf(line.c_str(), "%d,%lf,%zu,%lf,%lf,%lf", &step, &time, &points, &volume, &change, &mesh_volume), 6)
        << line;
    EXPECT_NEAR(mesh_volume, volume, 0.02 * volume);
    EXPECT_EQ(step, 8 * rows);
    EXPECT_NEAR(volume, 4.0 / 3.0 * M_PI * 0.15 * 0.15 * 0.15, 0.02 * volume);
    EXPECT_LT(std::abs(change), 0.02);
    char name[32];
    std::snprintf(name, sizeof(name), "frame_%05d.drc", step);
    auto frame = io::ReadPointCloudFile((out / name).string());
    ASSERT_TRUE(frame.ok()) << name << ": " << frame.status();
    EXPECT_EQ(frame->size(), points);
    EXPECT_TRUE(frame->has_normals());
    std::snprintf(name, sizeof(name), "frame_%05d_mesh.drc", step);
    auto mesh = io::ReadMeshFile((out / name).string());
    ASSERT_TRUE(mesh.ok()) << name << ": " << mesh.status();
    EXPECT_TRUE(core::AnalyzeTopology(*mesh).watertight()) << name;
    EXPECT_NEAR(core::EnclosedVolume(*mesh), mesh_volume, 1e-3 * mesh_volume) << name;  // Draco's quantization.
    ++rows;
  }
  EXPECT_EQ(rows, 3);
  EXPECT_FALSE(fs::exists(out / "summary.txt"));  // A quarter turn does not bring the shape back.

  // An uploaded interface (through the seed's gridline re-generation; the sphere above used the
  // default markers): the sampled sphere with its normals; without normals it is refused.
  const std::string cloud = WriteCloud("interface.ply", testing::SphereCloud(2000, 0.15, {0.5, 0.3, 0.5}));
  const ClientRun uploaded = Client(
      server.address(), "track --interface " + cloud + " --h 0.03125 --steps 2 --stride 1 --resampling gridlines -o " +
                            (dir_ / "up").string());
  EXPECT_EQ(uploaded.code, 0) << uploaded.output;
  EXPECT_TRUE(fs::exists(dir_ / "up" / "frame_00002.drc"));
  core::PointCloud bare = testing::SphereCloud(2000, 0.15, {0.5, 0.3, 0.5});
  bare.normals.clear();
  const ClientRun refused = Client(server.address(), "track --interface " + WriteCloud("bare.ply", bare) +
                                                         " --h 0.03125 -o " + (dir_ / "bare").string());
  EXPECT_NE(refused.code, 0);
  EXPECT_NE(refused.output.find("normals"), std::string::npos) << refused.output;
  const ClientRun unknown =
      Client(server.address(), "track --interface sphere --resampling lagrange -o " + (dir_ / "unknown").string());
  EXPECT_NE(unknown.code, 0);
  EXPECT_NE(unknown.output.find("resampling"), std::string::npos) << unknown.output;
}

TEST_F(EndToEnd, TrackThroughAnUploadedVelocityGrid) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  // A uniform field on a 2×2×2 grid: the sphere translates by v·t and keeps its volume.
  const Eigen::Vector3d v(0.002, -0.001, 0.0015);
  std::string vtk =
      "# vtk DataFile Version 3.0\nuniform\nASCII\nDATASET STRUCTURED_POINTS\nDIMENSIONS 2 2 2\n"
      "ORIGIN 0 0 0\nSPACING 1 1 1\nPOINT_DATA 8\nVECTORS velocity double\n";
  for (int i = 0; i < 8; ++i) vtk += "0.002 -0.001 0.0015\n";
  const std::string grid = (dir_ / "uniform.vtk").string();
  ASSERT_TRUE(io::WriteFileAtomically(grid, vtk).ok());
  const fs::path out = dir_ / "moved";
  const ClientRun r = Client(server.address(), "track --interface sphere --field " + grid +
                                                   " --h 0.03125 --dt 10 --steps 10 --stride 10 -o " + out.string());
  ASSERT_EQ(r.code, 0) << r.output;
  auto first = io::ReadPointCloudFile((out / "frame_00000.drc").string());
  auto last = io::ReadPointCloudFile((out / "frame_00010.drc").string());
  ASSERT_TRUE(first.ok() && last.ok());
  auto centroid = [](const core::PointCloud& c) {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (const auto& p : c.positions) sum += p.cast<double>();
    return Eigen::Vector3d(sum / static_cast<double>(c.size()));
  };
  const Eigen::Vector3d moved = centroid(*last) - centroid(*first);
  EXPECT_LT((moved - 100 * v).norm(), 0.25 * 0.03125) << moved.transpose();
  EXPECT_FALSE(fs::exists(out / "summary.txt"));  // No exact shape to compare with after a user field.

  // A field with a NaN is refused before the job is queued, naming the bad vector.
  std::string bad = vtk;
  bad.replace(bad.rfind("0.002"), 5, "nan");
  const std::string bad_grid = (dir_ / "bad.vtk").string();
  ASSERT_TRUE(io::WriteFileAtomically(bad_grid, bad).ok());
  const ClientRun refused = Client(
      server.address(), "track --interface sphere --field " + bad_grid + " --h 0.03125 -o " + (dir_ / "bad").string());
  EXPECT_NE(refused.code, 0);
  EXPECT_NE(refused.output.find("velocity: vector 7 is not finite"), std::string::npos) << refused.output;
}

// The seed's deformation test through the service: with modulation=reversal the field runs at
// full speed and reverses at T/2, so the sphere is stretched further at T/2 than with the
// default cos(pi t / T) (a wider front, more points), and both bring it back at t = T, where the
// summary measures it against the exact sphere.
TEST_F(EndToEnd, TrackRunsTheDeformationFieldReversedAtHalfPeriod) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
  std::map<std::string, size_t> half_points;
  for (const std::string modulation : {"cos", "reversal"}) {
    const fs::path out = dir_ / modulation;
    const ClientRun r = Client(server.address(),
                               "track --interface sphere --field deformation --period 1 "
                               "--modulation " +
                                   modulation + " --h 0.03125 --dt 0.025 --steps 40 --stride 20 -o " + out.string());
    ASSERT_EQ(r.code, 0) << r.output;
    auto half = io::ReadPointCloudFile((out / "frame_00020.drc").string());
    ASSERT_TRUE(half.ok()) << half.status();
    half_points[modulation] = half->size();
    auto summary = io::ReadFileBytes((out / "summary.txt").string());
    ASSERT_TRUE(summary.ok()) << modulation << ": " << summary.status();
    double e1 = -1;
    const size_t at = summary->find("e1_rel=");
    ASSERT_NE(at, std::string::npos) << *summary;
    ASSERT_EQ(std::sscanf(summary->c_str() + at, "e1_rel=%lf", &e1), 1) << *summary;
    EXPECT_LT(e1, 0.25) << modulation << ": the sphere did not come back; " << *summary;
  }
  EXPECT_GT(half_points["reversal"], half_points["cos"] * 11 / 10)
      << half_points["reversal"] << " vs " << half_points["cos"];
  const ClientRun refused =
      Client(server.address(),
             "track --interface sphere --field deformation --modulation sine -o " + (dir_ / "sine").string());
  EXPECT_NE(refused.code, 0);
  EXPECT_NE(refused.output.find("modulation"), std::string::npos) << refused.output;
  // The markers' spacing and gap reach the server, which refuses a gap not above the spacing.
  const ClientRun crossed =
      Client(server.address(),
             "track --interface sphere --marker-spacing 0.6 --marker-gap 0.5 -o " + (dir_ / "crossed").string());
  EXPECT_NE(crossed.code, 0);
  EXPECT_NE(crossed.output.find("marker_gap=0.5 must exceed marker_spacing=0.6"), std::string::npos) << crossed.output;
  // So does the gridline mode's re-generation bound: a stretch below 1 is refused.
  const ClientRun shrinking = Client(server.address(),
                                     "track --interface sphere --resampling gridlines "
                                     "--regeneration-stretch 0.5 -o " +
                                         (dir_ / "shrinking").string());
  EXPECT_NE(shrinking.code, 0);
  EXPECT_NE(shrinking.output.find("regeneration_stretch=0.5 is out of range"), std::string::npos) << shrinking.output;
}

TEST_F(EndToEnd, SizeLimitsAreEnforced) {
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data", {"--max-upload-mib", "1", "--max-points", "50000"}));
  const ClientRun too_big = Client(server.address(), "submit " + WriteCloud("big.ply", testing::SphereCloud(300000)));
  EXPECT_EQ(too_big.code, 1);
  EXPECT_NE(too_big.output.find("limit of 1048576 bytes"), std::string::npos) << too_big.output;
  const ClientRun too_many = Client(server.address(), "submit " + WriteCloud("many.ply", testing::SphereCloud(60000)));
  EXPECT_EQ(too_many.code, 1);
  EXPECT_NE(too_many.output.find("at most 50000"), std::string::npos) << too_many.output;
}

// A job whose server is killed runs again after the restart, its attempts counted (the result
// of such a job is checked in the job service's tests).
TEST_F(EndToEnd, AJobSurvivesKillMinusNine) {
  std::string id;
  {
    Server server;
    ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data"));
    id = SubmitLongJob(server.address());
    ASSERT_TRUE(WaitRunning(server.address(), id));
    server.Kill(SIGKILL);
  }
  Server restarted;
  ASSERT_NO_FATAL_FAILURE(restarted.Start(dir_ / "data"));
  ASSERT_TRUE(WaitRunning(restarted.address(), id));
  const ClientRun status = Client(restarted.address(), "status " + id);
  EXPECT_NE(status.output.find("attempts   2"), std::string::npos) << status.output;
  EXPECT_EQ(Client(restarted.address(), "cancel " + id).code, 0);
  EXPECT_EQ(Client(restarted.address(), "watch " + id).code, 2);  // Cancelled.
}

// A graceful stop (SIGTERM) puts the running job back in the queue without counting it as a
// crash; the next start runs it again.
TEST_F(EndToEnd, AGracefulStopRequeuesTheRunningJob) {
  std::string id;
  {
    Server server;
    ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data", {"--max-attempts", "1"}));
    id = SubmitLongJob(server.address());
    ASSERT_TRUE(WaitRunning(server.address(), id));
    server.Kill(SIGTERM);
  }
  Server restarted;
  ASSERT_NO_FATAL_FAILURE(restarted.Start(dir_ / "data", {"--max-attempts", "1"}));
  ASSERT_TRUE(WaitRunning(restarted.address(), id));
  EXPECT_EQ(Client(restarted.address(), "cancel " + id).code, 0);
}

// The checked-in parameter reference is what the tables generate: a table change that does not
// regenerate it (lsqsurfd --parameter-reference > docs/parameters.md) fails here.
// GET http://127.0.0.1:port/metrics over a plain socket; the body.
// A loopback connection to `port`; -1 when it cannot be made.
int ConnectLoopback(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0) return fd;
  ::close(fd);
  return -1;
}

// The body of the answer to GET /metrics naming `host`; its status line into `status` if given.
std::string ScrapeMetrics(int port, const std::string& host = "127.0.0.1", std::string* status = nullptr) {
  const int fd = ConnectLoopback(port);
  std::string response;
  if (fd >= 0) {
    const std::string request = "GET /metrics HTTP/1.0\r\nHost: " + host + "\r\n\r\n";
    if (::write(fd, request.data(), request.size()) == static_cast<ssize_t>(request.size())) {
      char buf[4096];
      for (ssize_t n; (n = ::read(fd, buf, sizeof(buf))) > 0;) response.append(buf, static_cast<size_t>(n));
    }
  }
  if (fd >= 0) ::close(fd);
  if (status != nullptr) *status = response.substr(0, response.find("\r\n"));
  const size_t body = response.find("\r\n\r\n");
  return body == std::string::npos ? "" : response.substr(body + 4);
}

// The value of the sample `name` whose labels include every one of `labels` ("k=\"v\""); -1 if none.
double MetricValue(const std::string& text, const std::string& name, const std::vector<std::string>& labels) {
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    if (line.rfind(name + "{", 0) != 0 && line.rfind(name + " ", 0) != 0) continue;
    const size_t close = line.find('}');
    const std::string label_text = close == std::string::npos ? "" : line.substr(0, close);
    if (!std::all_of(labels.begin(), labels.end(),
                     [&](const std::string& l) { return label_text.find(l) != std::string::npos; })) {
      continue;
    }
    return std::stod(line.substr(line.rfind(' ') + 1));
  }
  return -1;
}

TEST_F(EndToEnd, MetricsCountJobsCallsAndRejectionsBehindTheBoundedFront) {
  const int port = testing::FreeLoopbackPort();
  Server server;
  ASSERT_NO_FATAL_FAILURE(server.Start(dir_ / "data", {"--metrics-listen", "127.0.0.1:" + std::to_string(port)}));
  const std::string in = WriteCloud("sphere.ply", testing::SphereCloud(5000));
  const ClientRun r = Client(server.address(), "reconstruct " + in + " -o " + (dir_ / "m.ply").string());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(Client(server.address(), "status 0123456789abcdef").code, 0);  // NOT_FOUND.
  v1::JobSpec no_input;
  ASSERT_TRUE(client::SetMethod(&no_input, "iamls").ok());
  EXPECT_EQ(client::Client(server.address()).Submit(no_input, "").status().code(),
            absl::StatusCode::kInvalidArgument);  // A surface job needs a cloud.
  // The port is the HTTP front's: a silent connection holds nothing a scrape needs, and a page
  // that rebinds its name to the port is refused.
  const int silent = ConnectLoopback(port);
  ASSERT_GE(silent, 0);
  const std::string text = ScrapeMetrics(port);
  ::close(silent);
  ASSERT_FALSE(text.empty()) << "no answer on the metrics port";
  std::string refused;
  ScrapeMetrics(port, "rebound.example", &refused);
  EXPECT_NE(refused.find(" 421 "), std::string::npos) << refused;
  EXPECT_EQ(MetricValue(text, "lsqsurf_jobs", {"method=\"iamls\"", "state=\"succeeded\""}), 1) << text;
  EXPECT_EQ(MetricValue(text, "lsqsurf_queue_depth", {}), 0);
  EXPECT_EQ(MetricValue(text, "lsqsurf_job_duration_seconds_count", {"method=\"iamls\"", "state=\"succeeded\""}), 1);
  EXPECT_GE(MetricValue(text, "lsqsurf_stage_duration_seconds_count", {"method=\"iamls\""}), 1);
  EXPECT_EQ(MetricValue(text, "lsqsurf_rpc_errors_total", {"rpc=\"GetJob\"", "code=\"NOT_FOUND\""}), 1);
  EXPECT_EQ(MetricValue(text, "lsqsurf_rpc_errors_total", {"rpc=\"SubmitJob\"", "code=\"INVALID_ARGUMENT\""}), 1);
  EXPECT_GE(MetricValue(text, "lsqsurf_rpc_duration_seconds_count", {"rpc=\"SubmitJob\""}), 2);
  // The upload (a 5000-point Draco cloud) came in; the mesh went out.
  EXPECT_GT(MetricValue(text, "lsqsurf_received_bytes_total", {}), 10000);
  EXPECT_GT(MetricValue(text, "lsqsurf_sent_bytes_total", {}), 10000);
}

// What `lsqsurfd FLAG` prints, which must match the file under docs/ it generates; empty when
// either cannot be had (the failure is reported).
std::string GeneratedDoc(const std::string& flag, const std::string& doc) {
  FILE* p = ::popen((LSQSURFD_PATH " " + flag).c_str(), "r");
  EXPECT_NE(p, nullptr);
  if (p == nullptr) return {};
  std::string generated;
  std::array<char, 4096> buf;
  size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0) generated.append(buf.data(), n);
  EXPECT_EQ(::pclose(p), 0) << flag;
  auto docs = io::ReadFileBytes(LSQSURF_SOURCE_DIR "/docs/" + doc);
  EXPECT_TRUE(docs.ok()) << docs.status();
  if (!docs.ok()) return {};
  EXPECT_EQ(*docs, generated) << "regenerate docs/" << doc << " with lsqsurfd " << flag;
  return generated;
}

TEST(ParameterReference, TheDocsAreGeneratedFromTheTables) {
  const std::string generated = GeneratedDoc("--parameter-reference", "parameters.md");
  for (const char* method :
       {"## iamls", "## pu", "## ramls", "## apss", "## aamls", "## imls", "## track", "## View options"}) {
    EXPECT_NE(generated.find(method), std::string::npos) << method;
  }
}

TEST(LimitsReference, TheDocsAreGeneratedFromTheTable) {
  const std::string generated = GeneratedDoc("--limits-reference", "limits.md");
  for (const char* row : {"| `--max-queue` | 64 |", "| `--max-upload-mib` | 1024 |", "| `--min-free-mib` | 256 |"}) {
    EXPECT_NE(generated.find(row), std::string::npos) << row;
  }
}

// The README restates some limits' defaults in its prose and Security table ("`--max-queue` (64)",
// "(default 10)"); each number it gives must be the table's (docs/limits.md), "20M" for 20000000.
TEST(LimitsReference, TheReadmesDefaultsAreTheTables) {
  const std::string table = GeneratedDoc("--limits-reference", "limits.md");
  auto readme = io::ReadFileBytes(LSQSURF_SOURCE_DIR "/README.md");
  ASSERT_TRUE(readme.ok()) << readme.status();
  int compared = 0;
  for (size_t row = table.find("| `--"); row != std::string::npos; row = table.find("| `--", row + 1)) {
    const size_t flag_end = table.find('`', row + 3);
    const std::string flag = table.substr(row + 2, flag_end + 1 - (row + 2));  // "`--max-queue`"
    const size_t value_at = table.find("| ", flag_end) + 2;
    const std::string value = table.substr(value_at, table.find(' ', value_at) - value_at);
    for (size_t at = readme->find(flag + " ("); at != std::string::npos; at = readme->find(flag + " (", at + 1)) {
      std::string said = readme->substr(at + flag.size() + 2, readme->find(')', at) - (at + flag.size() + 2));
      if (said.starts_with("default ")) said = said.substr(8);
      if (said.empty() || said.find_first_not_of("0123456789.M") != std::string::npos) continue;  // Prose.
      if (said.back() == 'M') said = said.substr(0, said.size() - 1) + "000000";
      EXPECT_EQ(said, value) << "README: " << flag << " (" << said << "), the table: " << value;
      ++compared;
    }
  }
  EXPECT_GE(compared, 6);
}

// `lsqsurf sample`: points on the mesh with outward unit normals, as many as asked; the noise is
// Gaussian along the normal with σ the asked share of the diagonal.
TEST(ClientTool, SamplesACloudOnTheMeshWithTheAskedNoise) {
  const fs::path dir = testing::FreshTestDir("lsqsurf-sample");
  fs::create_directories(dir);
  const std::string mesh = (dir / "sphere.obj").string(), cloud = (dir / "cloud.ply").string();
  ASSERT_TRUE(io::WriteMeshFile(mesh, core::SphereMesh(60, 120)).ok());
  const std::string tool = LSQSURF_PATH;
  ASSERT_EQ(testing::Shell(tool + " sample " + mesh + " --points 5000 -o " + cloud).code, 0);
  auto exact = io::ReadPointCloudFile(cloud);
  ASSERT_TRUE(exact.ok()) << exact.status();
  ASSERT_EQ(exact->size(), 5000u);
  ASSERT_TRUE(exact->has_normals());
  for (size_t i = 0; i < exact->size(); ++i) {
    const double r = exact->positions[i].norm();
    EXPECT_GT(r, 0.998);  // On the facets: between the chords' depth (1 − cos(1.5°)) and the sphere.
    EXPECT_LT(r, 1.0 + 1e-6);
    EXPECT_NEAR(exact->normals[i].norm(), 1.0, 1e-5);
    EXPECT_GT(exact->normals[i].dot(exact->positions[i]) / r, 0.999);
  }
  ASSERT_EQ(testing::Shell(tool + " sample " + mesh + " --points 20000 --noise 0.01 --seed 7 -o " + cloud).code, 0);
  auto noisy = io::ReadPointCloudFile(cloud);
  ASSERT_TRUE(noisy.ok()) << noisy.status();
  double sum2 = 0;
  for (const auto& p : noisy->positions) sum2 += std::pow(p.norm() - 1.0, 2);
  const double sigma = 0.01 * 2 * std::sqrt(3.0);  // The sphere's box diagonal is 2√3.
  EXPECT_NEAR(std::sqrt(sum2 / static_cast<double>(noisy->size())), sigma, 0.05 * sigma);
  const testing::ClientRun bad = testing::Shell(tool + " sample " + mesh + " --noise 0.5 -o " + cloud);
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.output.find("--noise"), std::string::npos) << bad.output;
  fs::remove_all(dir);
}

TEST_F(EndToEnd, TokensMadeByTheCommandLineAreTakenAndReloadedOnSighup) {
  const std::string file = (dir_ / "tokens").string();
  const auto add = [&](const std::string& name, const std::string& extra) {
    const std::string token_file = (dir_ / (name + ".token")).string();
    ClientRun made = testing::Shell(std::string(LSQSURFD_PATH) + " tokens add " + file + " " + name + " " + extra +
                                    " >" + token_file);
    EXPECT_EQ(made.code, 0) << made.output;
    EXPECT_NE(made.output.find("shown only now"), std::string::npos) << made.output;
    return "--token-file " + token_file + " ";
  };
  const std::string alice = add("alice", "--max-jobs 3");
  Server server;
  server.Start(dir_ / "data", {"--auth-tokens", file});
  ClientRun info = Client(server.address(), alice + "info");
  ASSERT_EQ(info.code, 0) << info.output;
  EXPECT_NE(info.output.find("alice (user)"), std::string::npos) << info.output;
  EXPECT_NE(info.output.find("jobs             0 of 3"), std::string::npos) << info.output;
  ClientRun anonymous = Client(server.address(), "list");
  EXPECT_NE(anonymous.code, 0);
  EXPECT_NE(anonymous.output.find("needs a token"), std::string::npos) << anonymous.output;
  std::ofstream(dir_ / "garbled.token") << "lsq_12\n34\n";
  ClientRun garbled = Client(server.address(), "--token-file " + (dir_ / "garbled.token").string() + " list");
  EXPECT_EQ(garbled.code, 3);  // Refused by the client (a local error), not a crash.
  EXPECT_NE(garbled.output.find("token"), std::string::npos) << garbled.output;

  // A token added to the file is taken after SIGHUP; a revoked one is refused after the next.
  const std::string bob = add("bob", "--role admin");
  ASSERT_EQ(testing::Shell(std::string(LSQSURFD_PATH) + " tokens revoke " + file + " alice").code, 0);
  server.Signal(SIGHUP);
  bool reloaded = false;  // The server reloads on its own thread: wait (bounded) for it.
  for (int attempt = 0; attempt < 100 && !reloaded; ++attempt) {
    reloaded = Client(server.address(), bob + "list").code == 0;
    if (!reloaded) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_TRUE(reloaded);
  EXPECT_NE(Client(server.address(), alice + "list").code, 0);
  ClientRun listed = testing::Shell(std::string(LSQSURFD_PATH) + " tokens list " + file);
  EXPECT_NE(listed.output.find("bob"), std::string::npos);
  EXPECT_EQ(listed.output.find("alice"), std::string::npos);
}

TEST_F(EndToEnd, PlaintextOffLoopbackIsServedOnlyWhenAskedFor) {
  const std::string server = std::string(LSQSURFD_PATH) + " --data-dir " + (dir_ / "data").string();
  ClientRun refused = testing::Shell(server + " --listen 0.0.0.0:0");
  EXPECT_EQ(refused.code, 1);
  EXPECT_NE(refused.output.find("--plaintext"), std::string::npos) << refused.output;
  ClientRun half = testing::Shell(server + " --listen 127.0.0.1:0 --tls-cert x.pem");
  EXPECT_EQ(half.code, 1);
  EXPECT_NE(half.output.find("--tls-cert and --tls-key go together"), std::string::npos) << half.output;
  // The client, too, uses TLS off loopback unless asked not to: it fails to reach a plaintext
  // server rather than send a token in the clear.
  Server plain;
  plain.Start(dir_ / "data", {});
  ClientRun tls = Client(plain.address(), "--tls info");
  EXPECT_NE(tls.code, 0);
  EXPECT_EQ(Client(plain.address(), "info").code, 0);
}

}  // namespace
}  // namespace lsqsurf
