#include <gtest/gtest.h>

#include <cstdio>
#include <cstring>
#include <filesystem>
#include <random>

#include "worker/io/draco_codec.h"
#include "worker/io/draco_header.h"
#include "worker/io/files.h"
#include "worker/io/ply.h"

namespace lsqsurf::io {
namespace {

core::PointCloud RandomCloud(size_t n) {
  core::PointCloud c;
  std::mt19937 rng(9);
  std::uniform_real_distribution<float> u(-1, 1);
  core::ScalarAttribute intensity{"intensity", {}};
  for (size_t i = 0; i < n; ++i) {
    // Tie the attribute to the position so that reordering by the codec can be checked.
    const core::Vec3f p(u(rng), u(rng), u(rng));
    c.positions.push_back(p);
    c.normals.push_back(p.normalized());
    intensity.values.push_back(p.x() + 2 * p.y());
  }
  c.attributes.push_back(intensity);
  return c;
}

TEST(Draco, PointCloudRoundTripWithinQuantization) {
  const core::PointCloud cloud = RandomCloud(5000);
  auto bytes = EncodeDracoPointCloud(cloud, {});
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  EXPECT_LT(bytes->size(), cloud.size() * 28 / 2);  // Compressed, not the sequential fallback.
  auto back = DecodeDracoPointCloud(*bytes);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->size(), cloud.size());
  ASSERT_TRUE(back->has_normals());
  ASSERT_EQ(back->attributes.size(), 1u);
  EXPECT_EQ(back->attributes[0].name, "intensity");
  // Points come back reordered: check each against the attribute it carries.
  const float step = 2.0f / (1 << 16);
  for (size_t i = 0; i < back->size(); ++i) {
    const auto& p = back->positions[i];
    EXPECT_NEAR(back->attributes[0].values[i], p.x() + 2 * p.y(), 3 * 2.0f / (1 << 14) + 3 * step);
    EXPECT_GT(back->normals[i].dot(p.normalized()), 0.999f);
  }
}

// The unit square in the z = 0 plane, n × n quads split into two triangles each.
core::TriangleMesh GridMesh(int n) {
  core::TriangleMesh m;
  for (int j = 0; j <= n; ++j)
    for (int i = 0; i <= n; ++i)
      m.vertices.emplace_back(static_cast<float>(i) / static_cast<float>(n),
                              static_cast<float>(j) / static_cast<float>(n), 0.0f);
  for (int j = 0; j < n; ++j)
    for (int i = 0; i < n; ++i) {
      const auto a = static_cast<uint32_t>(j * (n + 1) + i);
      m.faces.push_back({a, a + 1, a + static_cast<uint32_t>(n) + 1});
      m.faces.push_back({a + 1, a + static_cast<uint32_t>(n) + 2, a + static_cast<uint32_t>(n) + 1});
    }
  return m;
}

TEST(Draco, MeshRoundTripKeepsConnectivity) {
  const core::TriangleMesh m = GridMesh(20);
  auto bytes = EncodeDracoMesh(m, {});
  ASSERT_TRUE(bytes.ok());
  auto back = DecodeDracoMesh(*bytes);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->vertices.size(), m.vertices.size());
  EXPECT_EQ(back->faces.size(), m.faces.size());
  double area = 0;
  for (const auto& f : back->faces) {
    area += 0.5 * (back->vertices[f[1]] - back->vertices[f[0]]).cross(back->vertices[f[2]] - back->vertices[f[0]]).z();
  }
  EXPECT_NEAR(area, 1.0, 1e-4);  // Same orientation (+z) and coverage.
  EXPECT_EQ(DecodeDracoMesh(*EncodeDracoPointCloud(RandomCloud(10), {})).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(Draco, TruncatedAndCorruptDataGiveErrors) {
  auto bytes = EncodeDracoPointCloud(RandomCloud(2000), {});
  ASSERT_TRUE(bytes.ok());
  for (size_t len : {size_t{0}, size_t{3}, size_t{10}, bytes->size() / 3, bytes->size() - 1}) {
    auto r = DecodeDracoPointCloud(std::string_view(*bytes).substr(0, len));
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << "length " << len;
  }
  EXPECT_FALSE(DecodeDracoPointCloud("definitely not draco").ok());
}

// Random corruption of an upload must give an error or a well-formed cloud, never a crash.
TEST(Draco, SurvivesRandomCorruption) {
  auto bytes = EncodeDracoPointCloud(RandomCloud(3000), {});
  ASSERT_TRUE(bytes.ok());
  std::mt19937 rng(5);
  for (int trial = 0; trial < 300; ++trial) {
    std::string mutated = *bytes;
    const int flips = 1 + static_cast<int>(rng() % 4);
    for (int f = 0; f < flips; ++f) mutated[rng() % mutated.size()] = static_cast<char>(rng() & 0xff);
    auto r = DecodeDracoPointCloud(mutated);
    if (r.ok()) {
      EXPECT_TRUE(r->normals.empty() || r->normals.size() == r->positions.size());
    }
  }
}

// The Debian `draco_decoder` tool, an independent decoder, reads what we write.
TEST(Draco, ReferenceDecoderReadsOurFiles) {
  const auto dir = std::filesystem::temp_directory_path() / ("lsqsurf-draco-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const core::PointCloud cloud = RandomCloud(1000);
  ASSERT_TRUE(WritePointCloudFile((dir / "c.drc").string(), cloud).ok());
  const std::string cmd = std::string(DRACO_DECODER_PATH) + " -i " + (dir / "c.drc").string() + " -o " +
                          (dir / "c.ply").string() + " > /dev/null 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0);
  auto decoded = ReadPointCloudFile((dir / "c.ply").string());
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(decoded->size(), cloud.size());
  std::filesystem::remove_all(dir);
}

// The counts read from the header, without Draco, are those of the data: for both point-cloud
// coders (kd-tree, sequential) and both mesh coders (Edgebreaker, sequential).
TEST(DracoHeader, ClaimsMatchTheEncodedData) {
  const core::PointCloud cloud = RandomCloud(777);
  for (int speed : {5, 10}) {
    auto bytes = EncodeDracoPointCloud(cloud, {.speed = speed});
    ASSERT_TRUE(bytes.ok());
    auto claim = ReadDracoClaim(*bytes);
    ASSERT_TRUE(claim.ok()) << claim.status();
    EXPECT_FALSE(claim->is_mesh);
    EXPECT_EQ(claim->points, cloud.size()) << "speed " << speed;
    // Float positions and normals (3 components) and one float scalar, 4 + 4 bytes a component.
    EXPECT_EQ(claim->attribute_bytes_per_point, 7u * 8u) << "speed " << speed;
  }
  const core::TriangleMesh mesh = GridMesh(9);
  for (int speed : {5, 10}) {
    auto bytes = EncodeDracoMesh(mesh, {.speed = speed});
    ASSERT_TRUE(bytes.ok());
    auto claim = ReadDracoClaim(*bytes);
    ASSERT_TRUE(claim.ok()) << claim.status();
    EXPECT_TRUE(claim->is_mesh);
    EXPECT_EQ(claim->points, mesh.vertices.size()) << "speed " << speed;
    EXPECT_EQ(claim->faces, mesh.faces.size()) << "speed " << speed;
  }
}

// A valid cloud whose point count is raised to a billion: Draco would allocate ~12 GB for it.
TEST(DracoHeader, InflatedPointCountIsRefusedBeforeDecoding) {
  auto bytes = EncodeDracoPointCloud(RandomCloud(500), {.position_bits = 11});
  ASSERT_TRUE(bytes.ok());
  auto claim = ReadDracoClaim(*bytes);
  ASSERT_TRUE(claim.ok());
  // The unnamed-attribute cloud has no metadata, so the count sits right after the 11-byte header.
  std::string inflated = *EncodeDracoPointCloud({RandomCloud(500).positions, {}, {}}, {.position_bits = 11});
  ASSERT_EQ(inflated[10] & 0x80, 0) << "metadata flag";
  const int32_t billion = 1'000'000'000;
  std::memcpy(inflated.data() + 11, &billion, sizeof(billion));
  auto inflated_claim = ReadDracoClaim(inflated);
  ASSERT_TRUE(inflated_claim.ok()) << inflated_claim.status();
  EXPECT_EQ(inflated_claim->points, 1'000'000'000u);
  auto decoded = DecodeDracoPointCloud(inflated);
  EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(decoded.status().message().find("claims 1000000000 points"), std::string_view::npos) << decoded.status();
  // The server's own point limit is a resource limit, told apart from corruption.
  auto limited = DecodeDracoPointCloud(*bytes, {.max_points = 499});
  EXPECT_EQ(limited.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_TRUE(DecodeDracoPointCloud(*bytes, {.max_points = 500}).ok());
}

TEST(DracoHeader, RefusesDeepMetadataOldVersionsAndTruncation) {
  // Header of a sequential cloud with metadata, then blocks nested 40 deep: no entries, one
  // nameless child each.
  std::string deep = std::string("DRACO") + '\x02' + '\x03' + '\x00' + '\x00' + '\x00' + '\x80';
  deep += '\x00';  // No attribute metadata.
  for (int level = 0; level < 40; ++level) deep += std::string("\x00\x01\x00", 3);
  auto claim = ReadDracoClaim(deep);
  EXPECT_EQ(claim.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(claim.status().message().find("nested"), std::string_view::npos) << claim.status();

  auto bytes = EncodeDracoPointCloud(RandomCloud(50), {});
  ASSERT_TRUE(bytes.ok());
  std::string old = *bytes;
  old[6] = 1;  // Bitstream 2.1.
  EXPECT_NE(ReadDracoClaim(old).status().message().find("version 2.1"), std::string_view::npos);
  // Before 2.3 the kd-tree coder carries a second, unchecked point count deep in the stream.
  std::string old_kd_tree = *bytes;
  ASSERT_EQ(old_kd_tree[8], 1) << "kd-tree coded";
  old_kd_tree[6] = 2;
  EXPECT_NE(ReadDracoClaim(old_kd_tree).status().message().find("bitstream 2.2"), std::string_view::npos);
  // Every prefix that cuts the counts or descriptors off is refused, never read past its end.
  for (size_t len = 0; len < 24; ++len) {
    EXPECT_FALSE(ReadDracoClaim(std::string_view(*bytes).substr(0, len)).ok()) << "length " << len;
  }
}

}  // namespace
}  // namespace lsqsurf::io
