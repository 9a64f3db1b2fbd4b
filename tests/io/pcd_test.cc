// PCD: files the Point Cloud Library wrote, a binary organized cloud laid out as PCL lays one
// out (padding, a descriptor, missing pixels, packed colour), round trips through the writer in
// all three encodings, and hostile headers and blocks.
#include "worker/io/pcd.h"

#include <gtest/gtest.h>
#include <lzf.h>

#include <bit>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>

#include "tests/test_dir.h"
#include "worker/io/files.h"
#include "worker/io/point_stream.h"

namespace lsqsurf::io {
namespace {

const std::string kData = LSQSURF_SOURCE_DIR "/tests/data/pcd/";

const core::ScalarAttribute* Find(const core::PointCloud& cloud, const std::string& name) {
  for (const auto& a : cloud.attributes) {
    if (a.name == name) return &a;
  }
  return nullptr;
}

// A scratch folder, removed with it.
struct ScratchDir {
  explicit ScratchDir(const std::string& prefix) : dir(testing::FreshTestDir(prefix)) {
    std::filesystem::create_directories(dir);
  }
  ~ScratchDir() { std::filesystem::remove_all(dir); }
  const std::filesystem::path& path() const { return dir; }
  std::filesystem::path dir;
};

template <typename T>
void Put(std::string& out, T v) {
  out.append(reinterpret_cast<const char*>(&v), sizeof v);
}

TEST(Pcd, ReadsTheFilesPclWrote) {
  // An RGB-D view, binary_compressed with packed rgba: 13,704 points a metre or so in front of
  // the camera (its frame: z forward), each with a colour.
  auto milk_bytes = ReadFileBytes(kData + "milk_color.pcd");
  ASSERT_TRUE(milk_bytes.ok());
  PcdInfo info;
  auto milk = ParsePcd(*milk_bytes, "milk_color.pcd", &info);
  ASSERT_TRUE(milk.ok()) << milk.status();
  EXPECT_EQ(info.encoding, PcdEncoding::kBinaryCompressed);
  EXPECT_EQ(milk->size(), 13704u);
  EXPECT_EQ(info.points, 13704u);
  EXPECT_FALSE(milk->has_normals());
  EXPECT_TRUE(info.has_viewpoint);
  const core::Box3 box = core::BoundingBox(milk->positions);
  EXPECT_GT(box.min().z(), 0.5);
  EXPECT_LT(box.max().z(), 1.5);
  EXPECT_LT(core::Diagonal(box), 0.5);  // A carton, not the room.
  for (const char* channel : {"red", "green", "blue"}) {
    const core::ScalarAttribute* a = Find(*milk, channel);
    ASSERT_NE(a, nullptr) << channel;
    ASSERT_EQ(a->values.size(), milk->size());
    float low = 255, high = 0;
    for (float v : a->values) {
      EXPECT_EQ(v, std::round(v));
      low = std::min(low, v);
      high = std::max(high, v);
    }
    EXPECT_GE(low, 0);
    EXPECT_LE(high, 255);
    EXPECT_GT(high - low, 50) << channel;  // A printed carton under room light, not one flat value.
  }
  EXPECT_EQ(Find(*milk, "alpha"), nullptr);

  auto lamp_bytes = ReadFileBytes(kData + "lamppost.pcd");
  ASSERT_TRUE(lamp_bytes.ok());
  auto lamp = ParsePcd(*lamp_bytes, "lamppost.pcd", &info);
  ASSERT_TRUE(lamp.ok()) << lamp.status();
  EXPECT_EQ(info.encoding, PcdEncoding::kAscii);
  ASSERT_EQ(lamp->size(), 1771u);
  EXPECT_EQ(lamp->positions[1], core::Vec3f(-10.015625f, 0, 0.042999268f));  // Its second data line.
  EXPECT_TRUE(lamp->attributes.empty());
}

// A 4 x 3 organized cloud as PCL writes pcl::PointXYZRGBNormal-like points in binary: padding
// after x y z, a packed F rgb, a U2 intensity, a 3-element descriptor, missing pixels as NaN.
TEST(Pcd, AnOrganizedBinaryCloudInPclsLayout) {
  std::string file =
      "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z _ rgb intensity hist\n"
      "SIZE 4 4 4 1 4 2 4\nTYPE F F F U F U F\nCOUNT 1 1 1 4 1 1 3\nWIDTH 4\nHEIGHT 3\n"
      "VIEWPOINT 0.5 -1 2 1 0 0 0\nPOINTS 12\nDATA binary\n";
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (int p = 0; p < 12; ++p) {
    const auto f = static_cast<float>(p);
    const bool missing = p == 1 || p == 6 || p == 11;
    for (float v : {missing ? nan : 0.25f * f, missing ? nan : 1.0f - f, missing ? nan : 2.0f + f}) Put(file, v);
    Put(file, uint32_t{0xdeadbeef});  // Padding.
    Put(file, std::bit_cast<float>(static_cast<uint32_t>((10 * p) << 16 | (p + 1) << 8 | (255 - p))));
    Put(file, static_cast<uint16_t>(1000 + p));
    for (float h : {1.0f, 2.0f, 3.0f}) Put(file, h);
  }
  PcdInfo info;
  auto cloud = ParsePcd(file, "organized.pcd", &info);
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  EXPECT_EQ(info.width, 4u);
  EXPECT_EQ(info.height, 3u);
  EXPECT_EQ(info.skipped_points, 3u);
  EXPECT_EQ(info.viewpoint[0], 0.5);
  EXPECT_EQ(info.viewpoint[2], 2);
  ASSERT_EQ(cloud->size(), 9u);
  ASSERT_EQ(cloud->attributes.size(), 4u);  // red green blue intensity; neither padding nor the descriptor.
  size_t kept = 0;
  for (int p = 0; p < 12; ++p) {
    if (p == 1 || p == 6 || p == 11) continue;
    const auto f = static_cast<float>(p);
    EXPECT_EQ(cloud->positions[kept], core::Vec3f(0.25f * f, 1.0f - f, 2.0f + f));
    EXPECT_EQ(Find(*cloud, "red")->values[kept], 10 * p);
    EXPECT_EQ(Find(*cloud, "green")->values[kept], p + 1);
    EXPECT_EQ(Find(*cloud, "blue")->values[kept], 255 - p);
    EXPECT_EQ(Find(*cloud, "intensity")->values[kept], 1000 + p);
    ++kept;
  }
}

core::PointCloud ColouredCloud(size_t n) {
  core::PointCloud cloud;
  for (const char* channel : {"red", "green", "blue", "intensity"}) cloud.attributes.push_back({channel, {}});
  for (size_t i = 0; i < n; ++i) {
    const float t = 0.37f * static_cast<float>(i);
    cloud.positions.emplace_back(std::cos(t), std::sin(t), 0.01f * static_cast<float>(i));
    cloud.normals.push_back(core::Vec3f(std::cos(t), std::sin(t), 0.5f).normalized());
    for (int c = 0; c < 3; ++c) cloud.attributes[c].values.push_back(static_cast<float>((i * (c + 3)) % 256));
    cloud.attributes[3].values.push_back(0.125f * static_cast<float>(i));
  }
  return cloud;
}

TEST(Pcd, EveryEncodingRoundTripsPositionsNormalsColourAndScalars) {
  const core::PointCloud cloud = ColouredCloud(2000);
  for (PcdEncoding encoding : {PcdEncoding::kAscii, PcdEncoding::kBinary, PcdEncoding::kBinaryCompressed}) {
    const std::string bytes = EncodePcd(cloud, encoding, {1, 2, 3, 1, 0, 0, 0});
    PcdInfo info;
    auto back = ParsePcd(bytes, "round.pcd", &info);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(info.encoding, encoding);
    EXPECT_EQ(back->positions, cloud.positions);
    ASSERT_TRUE(back->has_normals());
    for (size_t i = 0; i < cloud.size(); ++i) EXPECT_LT((back->normals[i] - cloud.normals[i]).norm(), 1e-6);
    ASSERT_EQ(back->attributes.size(), cloud.attributes.size());
    for (size_t a = 0; a < cloud.attributes.size(); ++a) {
      EXPECT_EQ(back->attributes[a].name, cloud.attributes[a].name);
      EXPECT_EQ(back->attributes[a].values, cloud.attributes[a].values);
    }
    EXPECT_EQ(info.viewpoint[1], 2);
  }
  // Compression does compress this cloud (its positions and colours repeat in pattern).
  EXPECT_LT(EncodePcd(cloud, PcdEncoding::kBinaryCompressed).size(), EncodePcd(cloud, PcdEncoding::kBinary).size());
}

TEST(Pcd, ANanNormalDropsTheNormalsAndTheStreamAgreesWithTheWholeRead) {
  core::PointCloud cloud = ColouredCloud(500);
  cloud.normals[321] = core::Vec3f::Constant(std::numeric_limits<float>::quiet_NaN());
  const ScratchDir dir("lsqsurf-pcd");
  const std::string path = (dir.path() / "c.pcd").string();
  ASSERT_TRUE(WriteFileAtomically(path, EncodePcd(cloud, PcdEncoding::kBinary, {4, 5, 6, 1, 0, 0, 0})).ok());
  PcdInfo info;
  auto whole = ParsePcd(*ReadFileBytes(path), path, &info);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_TRUE(info.normals_dropped);
  EXPECT_FALSE(whole->has_normals());
  auto stream = OpenPointStream(path);
  ASSERT_TRUE(stream.ok()) << stream.status();
  ASSERT_EQ((*stream)->sensor_positions().size(), 1u);
  EXPECT_EQ((*stream)->sensor_positions()[0], core::Vec3d(4, 5, 6));
  core::PointCloud streamed;
  for (;;) {
    auto chunk = (*stream)->Next(77);
    ASSERT_TRUE(chunk.ok()) << chunk.status();
    if (chunk->empty()) break;
    EXPECT_FALSE(chunk->has_normals());
    ASSERT_EQ(chunk->attributes.size(), 4u);
    streamed.positions.insert(streamed.positions.end(), chunk->positions.begin(), chunk->positions.end());
    if (streamed.attributes.empty())
      streamed.attributes = chunk->attributes;
    else
      for (size_t a = 0; a < 4; ++a) {
        auto& to = streamed.attributes[a].values;
        to.insert(to.end(), chunk->attributes[a].values.begin(), chunk->attributes[a].values.end());
      }
  }
  EXPECT_EQ(streamed.positions, whole->positions);
  for (size_t a = 0; a < 4; ++a) EXPECT_EQ(streamed.attributes[a].values, whole->attributes[a].values);
}

void ExpectRefused(const std::string& bytes, const std::string& words) {
  auto cloud = ParsePcd(bytes, "bad.pcd");
  ASSERT_FALSE(cloud.ok()) << words;
  EXPECT_EQ(cloud.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(cloud.status().message()).find(words), std::string::npos) << cloud.status();
}

std::string Header(const std::string& counts, const std::string& data) {
  return "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n" + counts + "DATA " + data + "\n";
}

TEST(Pcd, HostileFilesAreRefusedBeforeTheyCostMemory) {
  ExpectRefused(Header("WIDTH 10\nHEIGHT 2\nPOINTS 5\n", "ascii"), "is not WIDTH");
  ExpectRefused(Header("WIDTH 4294967296\nHEIGHT 4294967297\n", "ascii"), "overflows");
  ExpectRefused(Header("WIDTH 3\nHEIGHT 1\n", "ascii") + "1 2 3\n4 5\n", "has 2 values, not 3");
  ExpectRefused(Header("WIDTH 3\nHEIGHT 1\n", "ascii") + "1 2 3\n", "ends after 1 of the 3 points");
  ExpectRefused(Header("WIDTH 2\nHEIGHT 1\n", "ascii") + "1 2 3\n4 five 6\n", "'five' in field y");
  ExpectRefused(Header("WIDTH 1000000000\nHEIGHT 1\n", "binary") + std::string(120, '\0'), "holds only 10");
  ExpectRefused("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nDATA ascii\n1 2\n", "no single x, y and z");
  ExpectRefused("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nWIDTH 1\nDATA ascii\n", "is not 1, 2, 4 or 8");
  ExpectRefused("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F\nWIDTH 1\nDATA ascii\n", "gives 3 sizes, 2 types");
  ExpectRefused(Header("WIDTH 1\nHEIGHT 1\n", "lzma"), "unknown encoding 'lzma'");
  ExpectRefused("VERSION 0.7\nFIELDS x y z\n", "ends before its DATA line");

  // A small block that claims to inflate to 1.2 GB: refused before the buffer is allocated.
  std::string bomb = Header("WIDTH 100000000\nHEIGHT 1\n", "binary_compressed");
  Put(bomb, uint32_t{1000});
  Put(bomb, uint32_t{1200000000});
  ExpectRefused(bomb + std::string(1000, '\0'), "more than LZF can");
  // A block that does inflate, but past the size its header gives.
  std::string values(1200, '\0');
  for (size_t i = 0; i < values.size(); ++i) values[i] = static_cast<char>(i % 7);
  std::string packed(2000, '\0');
  const unsigned size = lzf_compress(values.data(), 1200, packed.data(), 2000);
  ASSERT_GT(size, 0u);
  std::string over = Header("WIDTH 50\nHEIGHT 1\n", "binary_compressed");  // 600 bytes declared.
  Put(over, static_cast<uint32_t>(size));
  Put(over, uint32_t{600});
  ExpectRefused(over + packed.substr(0, size), "does not inflate to its declared 600 bytes");
  std::string lying = Header("WIDTH 50\nHEIGHT 1\n", "binary_compressed");
  Put(lying, static_cast<uint32_t>(size + 100));
  Put(lying, uint32_t{600});
  ExpectRefused(lying + packed.substr(0, size), "the file holds");
}

TEST(Pcd, FilesByExtensionAndTheFormatsWithoutAReader) {
  const ScratchDir dir("lsqsurf-pcd-files");
  const std::string path = (dir.path() / "c.PCD").string();
  const core::PointCloud cloud = ColouredCloud(50);
  ASSERT_TRUE(WritePointCloudFile(path, cloud).ok());
  auto back = ReadPointCloudFile(path);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->positions, cloud.positions);
  core::TriangleMesh mesh;
  mesh.vertices = cloud.positions;
  mesh.faces = {{0, 1, 2}};
  EXPECT_EQ(WriteMeshFile(path, mesh).code(), absl::StatusCode::kInvalidArgument);
  for (const auto& [name, advice] : {std::pair{"scan.laz", "laszip -i in.laz -o out.las"},
                                     std::pair{"scan.e57", "convert the file to .ply, .pcd, .las or .ptx"}}) {
    auto refused = ReadPointCloudFile((dir.path() / name).string());
    ASSERT_FALSE(refused.ok());
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(std::string(refused.status().message()).find(advice), std::string::npos) << refused.status();
  }
}

}  // namespace
}  // namespace lsqsurf::io
