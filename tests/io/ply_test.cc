#include "worker/io/ply.h"

#include <gtest/gtest.h>

#include <random>

namespace lsqsurf::io {
namespace {

core::TriangleMesh SampleMesh() {
  core::TriangleMesh m;
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(-10, 10);
  for (int i = 0; i < 50; ++i) {
    m.vertices.emplace_back(u(rng), u(rng), u(rng));
    m.normals.push_back(core::Vec3f(u(rng), u(rng), u(rng)).normalized());
  }
  m.vertex_attributes.push_back({"quality", std::vector<float>(50)});
  for (auto& v : m.vertex_attributes[0].values) v = u(rng);
  for (uint32_t i = 0; i + 2 < 50; ++i) m.faces.push_back({i, i + 1, i + 2});
  return m;
}

void ExpectSame(const core::TriangleMesh& a, const core::TriangleMesh& b) {
  ASSERT_EQ(a.vertices.size(), b.vertices.size());
  ASSERT_EQ(a.normals.size(), b.normals.size());
  ASSERT_EQ(a.faces, b.faces);
  for (size_t i = 0; i < a.vertices.size(); ++i) {
    EXPECT_EQ(a.vertices[i], b.vertices[i]);  // Bit-exact, ascii included.
    EXPECT_EQ(a.normals[i], b.normals[i]);
  }
  ASSERT_EQ(a.vertex_attributes.size(), b.vertex_attributes.size());
  EXPECT_EQ(a.vertex_attributes[0].name, b.vertex_attributes[0].name);
  EXPECT_EQ(a.vertex_attributes[0].values, b.vertex_attributes[0].values);
}

class PlyRoundTrip : public ::testing::TestWithParam<PlyFormat> {};

TEST_P(PlyRoundTrip, IsLossless) {
  const auto mesh = SampleMesh();
  auto back = ParsePly(EncodePly(mesh, GetParam()), "test.ply");
  ASSERT_TRUE(back.ok()) << back.status();
  ExpectSame(mesh, *back);
}

INSTANTIATE_TEST_SUITE_P(AllFormats, PlyRoundTrip,
                         ::testing::Values(PlyFormat::kAscii, PlyFormat::kBinaryLittleEndian,
                                           PlyFormat::kBinaryBigEndian));

TEST(Ply, ReadsOtherTypesQuadsAndSkipsUnknownElements) {
  const std::string text =
      "ply\nformat ascii 1.0\ncomment hi\nelement vertex 4\nproperty double x\nproperty double y\n"
      "property double z\nproperty uchar red\nelement face 1\nproperty list uchar uint vertex_index\n"
      "element camera 1\nproperty float k\nend_header\n0 0 0 255\n1 0 0 0\n1 1 0 0\n0 1 0 0\n"
      "4 0 1 2 3\n7.5\n";
  auto m = ParsePly(text, "quad.ply");
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->vertices.size(), 4u);
  EXPECT_EQ(m->faces.size(), 2u);
  ASSERT_EQ(m->vertex_attributes.size(), 1u);
  EXPECT_EQ(m->vertex_attributes[0].values[0], 255.0f);
}

void ExpectError(const std::string& bytes, const std::string& fragment) {
  auto m = ParsePly(bytes, "bad.ply");
  ASSERT_FALSE(m.ok());
  EXPECT_EQ(m.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(m.status().message()).find(fragment), std::string::npos) << m.status();
}

TEST(Ply, ErrorsNameTheProblemAndPlace) {
  ExpectError("PLY\n", "not a PLY file");
  ExpectError("ply\nformat ascii 1.0\nelement vertex 1\nproperty flot x\nend_header\n", "line 4");
  ExpectError("ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nproperty float z\nend_header\n1 2\n",
              "lacks x, y or z");
  ExpectError(
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n1 2 3\n1 2 oops\n",
      "line 9");
  ExpectError(
      "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
      "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
      "refers to vertex 7");
  ExpectError(
      "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\n"
      "property float y\nproperty float z\nend_header\n",
      "too short");
  ExpectError("ply\nformat ascii 1.0\nelement vertex 1\n", "no end_header");
}

TEST(Ply, EveryTruncationOfABinaryFileFailsCleanly) {
  const std::string full = EncodePly(SampleMesh(), PlyFormat::kBinaryLittleEndian);
  for (size_t len = 0; len < full.size(); len += 7) {
    auto m = ParsePly(std::string_view(full).substr(0, len), "cut.ply");
    EXPECT_FALSE(m.ok()) << "length " << len;
  }
}

// Random byte corruption of every format variant: the parser may accept or refuse, but must
// never read out of bounds (the sanitizer build checks) or return an inconsistent mesh.
TEST(Ply, SurvivesRandomCorruption) {
  std::mt19937 rng(21);
  for (PlyFormat format : {PlyFormat::kAscii, PlyFormat::kBinaryLittleEndian, PlyFormat::kBinaryBigEndian}) {
    const std::string original = EncodePly(SampleMesh(), format);
    for (int trial = 0; trial < 300; ++trial) {
      std::string bytes = original;
      const int flips = 1 + static_cast<int>(rng() % 4);
      for (int f = 0; f < flips; ++f) {
        bytes[rng() % bytes.size()] = static_cast<char>(rng() & 0xff);
      }
      auto m = ParsePly(bytes, "fuzz.ply");
      if (!m.ok()) continue;
      for (const auto& face : m->faces) {
        for (uint32_t v : face) ASSERT_LT(v, m->vertices.size());
      }
    }
  }
}

}  // namespace
}  // namespace lsqsurf::io
