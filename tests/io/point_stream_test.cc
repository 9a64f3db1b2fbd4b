// Files read a chunk at a time give the points the whole-file parsers give, in order.
#include "worker/io/point_stream.h"

#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>

#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/io/files.h"
#include "worker/io/mesh_part.h"
#include "worker/io/obj_xyz.h"
#include "worker/io/ply.h"

namespace lsqsurf::io {
namespace {

class PointStreamTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-point-stream");
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  std::string Write(const std::string& name, const std::string& bytes) {
    const std::string path = (dir_ / name).string();
    EXPECT_TRUE(WriteFileAtomically(path, bytes).ok());
    return path;
  }

  // Every chunk of `path` read `per_chunk` points at a time, joined.
  static core::PointCloud Joined(const std::string& path, size_t per_chunk, size_t* chunks = nullptr) {
    auto stream = OpenPointStream(path);
    EXPECT_TRUE(stream.ok()) << stream.status();
    core::PointCloud all;
    if (!stream.ok()) return all;
    for (size_t n = 0;; ++n) {
      auto chunk = (*stream)->Next(per_chunk);
      EXPECT_TRUE(chunk.ok()) << chunk.status();
      if (!chunk.ok() || chunk->empty()) {
        if (chunks != nullptr) *chunks = n;
        break;
      }
      EXPECT_LE(chunk->size(), per_chunk);
      all.positions.insert(all.positions.end(), chunk->positions.begin(), chunk->positions.end());
      all.normals.insert(all.normals.end(), chunk->normals.begin(), chunk->normals.end());
    }
    return all;
  }

  std::filesystem::path dir_;
};

// A cloud with a scalar per point and faces after the vertices, as scanners and mesh tools write.
core::TriangleMesh Sample() {
  core::TriangleMesh mesh = MeshFromCloud(testing::SphereCloud(5000));
  mesh.vertex_attributes.push_back({"intensity", std::vector<float>(mesh.vertices.size(), 0.5f)});
  for (uint32_t i = 0; i + 2 < 300; i += 3) mesh.faces.push_back({i, i + 1, i + 2});
  return mesh;
}

TEST_F(PointStreamTest, PlyInEveryFormatGivesThePointsOfTheWholeFile) {
  const core::TriangleMesh mesh = Sample();
  for (PlyFormat format : {PlyFormat::kAscii, PlyFormat::kBinaryLittleEndian, PlyFormat::kBinaryBigEndian}) {
    const std::string bytes = EncodePly(mesh, format);
    const std::string path = Write("cloud.ply", bytes);
    auto whole = ParsePly(bytes, path);
    ASSERT_TRUE(whole.ok()) << whole.status();
    size_t chunks = 0;
    const core::PointCloud streamed = Joined(path, 777, &chunks);
    EXPECT_EQ(chunks, (mesh.vertices.size() + 776) / 777);
    EXPECT_EQ(streamed.positions, whole->vertices);
    EXPECT_EQ(streamed.normals, whole->normals);
  }
}

TEST_F(PointStreamTest, XyzGivesThePointsOfTheWholeFile) {
  const std::string text = EncodeXyz(testing::SphereCloud(3000));
  const std::string path = Write("cloud.xyz", "# a comment line\n" + text);
  auto whole = ParseXyz(text, path);
  ASSERT_TRUE(whole.ok());
  const core::PointCloud streamed = Joined(path, 1000);
  EXPECT_EQ(streamed.positions, whole->positions);
  EXPECT_EQ(streamed.normals, whole->normals);
}

// Files that cannot be read in order are read whole and still handed out in chunks.
TEST_F(PointStreamTest, VerticesAfterAnotherElementAndObjFilesAreReadWhole) {
  const core::TriangleMesh mesh = Sample();
  const std::string obj = Write("cloud.obj", EncodeObj(mesh));
  const core::PointCloud streamed = Joined(obj, 1000);
  auto whole = ReadPointCloudFile(obj);
  ASSERT_TRUE(whole.ok());
  EXPECT_EQ(streamed.positions, whole->positions);

  const std::string material_first =
      "ply\nformat ascii 1.0\nelement material 1\nproperty uchar red\nelement vertex 3\n"
      "property float x\nproperty float y\nproperty float z\nend_header\n200\n0 0 0\n1 0 0\n0 1 0\n";
  const core::PointCloud three = Joined(Write("material_first.ply", material_first), 2);
  ASSERT_EQ(three.positions.size(), 3u);
  EXPECT_EQ(three.positions[1], core::Vec3f(1, 0, 0));
}

TEST_F(PointStreamTest, BrokenFilesNameTheFileAndThePlace) {
  const std::string bytes = EncodePly(Sample(), PlyFormat::kBinaryLittleEndian);
  // Cut inside the vertices: refused when the stream opens, before any point is sent.
  const std::string cut = Write("cut.ply", bytes.substr(0, bytes.size() / 2));
  auto stream = OpenPointStream(cut);
  ASSERT_FALSE(stream.ok());
  EXPECT_NE(stream.status().message().find("cut.ply"), std::string::npos) << stream.status();
  EXPECT_NE(stream.status().message().find("truncated"), std::string::npos) << stream.status();

  const std::string bad = Write("bad.xyz", "0 0 0\n1 0 0\n1 x 0\n");
  auto xyz = OpenPointStream(bad);
  ASSERT_TRUE(xyz.ok());
  auto chunk = (*xyz)->Next(2);
  ASSERT_TRUE(chunk.ok());
  EXPECT_EQ(chunk->size(), 2u);
  const absl::Status third = (*xyz)->Next(2).status();
  EXPECT_EQ(third.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(third.message().find("line 3"), std::string::npos) << third;
  EXPECT_EQ(OpenPointStream((dir_ / "missing.ply").string()).status().code(), absl::StatusCode::kNotFound);
}

TEST(MeshPart, RoundTripsAndRefusesWhatDoesNotFollowOn) {
  const std::vector<core::Vec3f> vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  const std::vector<core::Vec3f> normals(3, core::Vec3f(0, 0, 1));
  const std::vector<core::ScalarAttribute> attributes = {{"degree", {1, 2, 3}}};
  const std::vector<std::array<int64_t, 3>> faces = {{7, 10, 11}, {10, 11, 12}};  // 7: a vertex of an earlier part.
  const std::string bytes = EncodeMeshPart(10, vertices, normals, attributes, faces);
  auto part = DecodeMeshPart(bytes);
  ASSERT_TRUE(part.ok()) << part.status();
  EXPECT_EQ(part->first_vertex, 10);
  EXPECT_EQ(part->vertices, vertices);
  EXPECT_EQ(part->normals, normals);
  ASSERT_EQ(part->attributes.size(), 1u);
  EXPECT_EQ(part->attributes[0].name, "degree");
  EXPECT_EQ(part->attributes[0].values, attributes[0].values);
  EXPECT_EQ(part->faces, faces);
  // A face naming a vertex of a later part, and every truncation, are refused.
  const std::vector<std::array<int64_t, 3>> ahead = {{10, 11, 13}};
  EXPECT_FALSE(DecodeMeshPart(EncodeMeshPart(10, vertices, normals, attributes, ahead)).ok());
  for (size_t cut = 0; cut < bytes.size(); cut += 7) EXPECT_FALSE(DecodeMeshPart(bytes.substr(0, cut)).ok()) << cut;

  // Read field by field as FetchResultRequest's comment lays the part out, as a client author
  // would, with nothing of this project's: it ends exactly at the last face.
  size_t pos = 0;
  auto take = [&](size_t n) {
    const std::string field = bytes.substr(pos, n);
    pos += n;
    return field;
  };
  auto u64 = [&] {
    uint64_t v = 0;
    std::memcpy(&v, take(8).data(), 8);
    return v;
  };
  EXPECT_EQ(take(4), "LQM1");
  EXPECT_EQ(static_cast<int64_t>(u64()), 10);  // first_vertex
  const uint64_t n = u64();                    // positions
  EXPECT_EQ(n, 3u);
  take(n * 12);
  EXPECT_EQ(u64(), n);  // normals
  take(n * 12);
  EXPECT_EQ(u64(), 1u);  // attributes
  const uint64_t name_length = u64();
  EXPECT_EQ(take(name_length), "degree");
  EXPECT_EQ(u64(), n);  // its values, counted again
  take(n * 4);
  EXPECT_EQ(u64(), 2u);  // faces
  take(2 * 24);
  EXPECT_EQ(pos, bytes.size());
}

}  // namespace
}  // namespace lsqsurf::io
