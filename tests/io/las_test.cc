// LAS: files laid out by an independent writer (tests/data/las/make_las.py: VLRs and padding
// before the points, georeferenced coordinates, extra bytes, a 1.4 file without legacy counts,
// 8-bit colour in 16-bit fields, withheld and noise points), round trips through the writer,
// streaming, and hostile headers.
#include "worker/io/las.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <filesystem>

#include "tests/test_dir.h"
#include "worker/io/files.h"
#include "worker/io/point_stream.h"

namespace lsqsurf::io {
namespace {

const std::string kData = LSQSURF_SOURCE_DIR "/tests/data/las/";
constexpr int kPoints = 100;  // make_las.py's N.

const core::ScalarAttribute* Find(const core::PointCloud& cloud, const std::string& name) {
  for (const auto& a : cloud.attributes) {
    if (a.name == name) return &a;
  }
  return nullptr;
}

// The points make_las.py keeps: not withheld (42), not noise (i mod 10 == 3).
std::vector<int> KeptIndices() {
  std::vector<int> kept;
  for (int i = 0; i < kPoints; ++i) {
    if (i != 42 && i % 10 != 3) kept.push_back(i);
  }
  return kept;
}

struct Expected {
  std::string file;
  double x0, y0;
  int colour_bits;  // 0: none.
};

class LasFiles : public ::testing::TestWithParam<Expected> {};

TEST_P(LasFiles, ReadTheIndependentWritersFiles) {
  const Expected& e = GetParam();
  auto bytes = ReadFileBytes(kData + e.file);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  LasInfo info;
  auto cloud = ParseLas(*bytes, e.file, &info);
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  EXPECT_EQ(info.points, static_cast<uint64_t>(kPoints));
  EXPECT_EQ(info.withheld_points, 1u);
  EXPECT_EQ(info.noise_points, 10u);
  EXPECT_EQ(info.generating_software, "lsqsurf tests independent writer");
  const std::vector<int> kept = KeptIndices();
  ASSERT_EQ(cloud->size(), kept.size());
  // Georeferenced coordinates (500,000 / 4,000,000) are moved by whole units; small ones not.
  const bool moved = e.x0 > 1e5;
  EXPECT_EQ(info.shift[0] != 0, moved);
  const auto* intensity = Find(*cloud, "intensity");
  const auto* classification = Find(*cloud, "classification");
  ASSERT_NE(intensity, nullptr);
  ASSERT_NE(classification, nullptr);
  const auto channels = core::ColourChannels(cloud->attributes, cloud->size());
  EXPECT_EQ(channels[0] != nullptr, e.colour_bits != 0);
  // The 1.4 file describes its extra bytes: two fields become attributes by their names (made
  // safe), scale and offset applied; its undocumented bytes and the other files' stay unread.
  const bool described = e.file.starts_with("extra");
  const auto* amplitude = Find(*cloud, "Amplitude");
  const auto* deviation = Find(*cloud, "Deviation__dB_");
  ASSERT_EQ(amplitude != nullptr, described);
  ASSERT_EQ(deviation != nullptr, described);
  EXPECT_EQ(cloud->attributes.size(), (e.colour_bits != 0 ? 3u : 0u) + 2u + (described ? 2u : 0u));
  EXPECT_EQ(info.colour_8bit, e.colour_bits == 8);
  for (size_t k = 0; k < kept.size(); ++k) {
    const int i = kept[k];
    const double x = e.x0 + 0.25 * i - info.shift[0], y = e.y0 + 0.5 * (i % 10) - info.shift[1];
    const double z = 100 + 0.01 * i - info.shift[2];
    // The file's quantum is 0.01 in x and y, 0.001 in z: the points keep it after the move.
    EXPECT_NEAR(cloud->positions[k].x(), x, 0.006) << i;
    EXPECT_NEAR(cloud->positions[k].y(), y, 0.006) << i;
    EXPECT_NEAR(cloud->positions[k].z(), z, 0.0006) << i;
    EXPECT_EQ(intensity->values[k], static_cast<float>(100 * i));
    EXPECT_EQ(classification->values[k], 2.0f);
    if (described) {
      EXPECT_EQ(amplitude->values[k], static_cast<float>(1.5 * i + 2)) << i;
      EXPECT_EQ(deviation->values[k], static_cast<float>(-i)) << i;
    }
    if (channels[0] != nullptr) {
      const float want[3] = {static_cast<float>((i * 2) % 256), static_cast<float>((255 - i) % 256),
                             static_cast<float>((i * 7) % 256)};
      for (int c = 0; c < 3; ++c) EXPECT_NEAR(channels[c]->values[k], want[c], 1e-3) << i;
    }
  }
}

INSTANTIATE_TEST_SUITE_P(All, LasFiles,
                         ::testing::Values(Expected{"utm_1_2_format1.las", 500000.0, 4000000.0, 0},
                                           Expected{"local_1_3_format2.las", 10.0, 20.0, 16},
                                           Expected{"extra_1_4_format8.las", 1.5, -2.5, 8}));

core::PointCloud ColouredGrid(int n) {
  core::PointCloud cloud;
  cloud.attributes = {{"red", {}}, {"green", {}}, {"blue", {}}, {"intensity", {}}, {"classification", {}}};
  for (int i = 0; i < n; ++i) {
    cloud.positions.emplace_back(0.1f * static_cast<float>(i % 17), 0.05f * static_cast<float>(i / 17),
                                 std::sin(0.3f * static_cast<float>(i)));
    const float v[5] = {static_cast<float>(i % 256), static_cast<float>((3 * i) % 256),
                        static_cast<float>((255 - i % 256)), static_cast<float>(i * 11 % 65536), 2.0f};
    for (int a = 0; a < 5; ++a) cloud.attributes[a].values.push_back(v[a]);
  }
  return cloud;
}

TEST(Las, RoundTripsThroughItsWriterInBothVersions) {
  const core::PointCloud cloud = ColouredGrid(300);
  for (const auto& [minor, format] : {std::pair{2, 3}, std::pair{4, 7}, std::pair{4, 10}, std::pair{2, 0}}) {
    LasInfo info;
    auto back = ParseLas(EncodeLas(cloud, {.version_minor = minor, .point_format = format}), "round.las", &info);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(info.version_minor, minor);
    EXPECT_EQ(info.point_format, format);
    ASSERT_EQ(back->size(), cloud.size());
    for (size_t i = 0; i < cloud.size(); ++i) {
      EXPECT_NEAR((back->positions[i] - cloud.positions[i]).norm(), 0.0, 1e-6) << i;
    }
    const bool colour = format != 0;
    ASSERT_EQ(core::ColourChannels(back->attributes, back->size())[0] != nullptr, colour);
    for (size_t a = colour ? 0 : 3; a < cloud.attributes.size(); ++a) {
      const auto* got = Find(*back, cloud.attributes[a].name);
      ASSERT_NE(got, nullptr) << cloud.attributes[a].name;
      EXPECT_EQ(got->values, cloud.attributes[a].values) << cloud.attributes[a].name;
    }
  }
}

TEST(Las, StreamsInChunksAsItReadsWhole) {
  const std::filesystem::path dir = testing::FreshTestDir("lsqsurf-las");
  std::filesystem::create_directories(dir);
  const std::string path = (dir / "streamed.las").string();
  const core::PointCloud cloud = ColouredGrid(1000);
  ASSERT_TRUE(WritePointCloudFile(path, cloud).ok());
  auto stream = OpenPointStream(path);
  ASSERT_TRUE(stream.ok()) << stream.status();
  size_t total = 0;
  for (;;) {
    auto chunk = (*stream)->Next(97);
    ASSERT_TRUE(chunk.ok()) << chunk.status();
    if (chunk->size() == 0) break;
    EXPECT_LE(chunk->size(), 97u);
    EXPECT_EQ(chunk->attributes.size(), 5u);
    for (size_t i = 0; i < chunk->size(); ++i) {
      EXPECT_NEAR((chunk->positions[i] - cloud.positions[total + i]).norm(), 0.0, 1e-6);
    }
    total += chunk->size();
  }
  EXPECT_EQ(total, cloud.size());
  EXPECT_EQ((*stream)->coordinate_shift(), (std::array<double, 3>{0, 0, 0}));
  auto moved = OpenPointStream(kData + "utm_1_2_format1.las");
  ASSERT_TRUE(moved.ok());
  EXPECT_EQ((*moved)->coordinate_shift()[0], std::round(500000.0 + 0.25 * 99 / 2));
  std::filesystem::remove_all(dir);
}

void ExpectRefused(const std::string& bytes, const std::string& words) {
  auto cloud = ParseLas(bytes, "bad.las");
  ASSERT_FALSE(cloud.ok()) << words;
  EXPECT_EQ(cloud.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(cloud.status().message()).find(words), std::string::npos) << cloud.status();
}

template <typename T>
std::string With(std::string bytes, size_t at, T v) {
  std::memcpy(bytes.data() + at, &v, sizeof v);
  return bytes;
}

TEST(Las, HostileHeadersAreRefusedBeforeAPointIsRead) {
  const std::string good = EncodeLas(ColouredGrid(50), {.version_minor = 4, .point_format = 7});
  ASSERT_TRUE(ParseLas(good, "good.las").ok());
  ExpectRefused("LASF", "not a LAS file");
  ExpectRefused(std::string(300, 'x'), "not a LAS file");
  ExpectRefused(With<uint8_t>(good, 25, 9), "version 1.9");
  ExpectRefused(With<uint16_t>(good, 94, 100), "header size 100");
  ExpectRefused(With<uint32_t>(good, 96, 1u << 30), "offset to point data");
  ExpectRefused(With<uint8_t>(good, 104, 0x87), "LAZ-compressed");
  ExpectRefused(With<uint8_t>(good, 104, 11), "format 11");
  ExpectRefused(With<uint16_t>(good, 105, 20), "shorter than format 7's 36");
  ExpectRefused(With<uint64_t>(good, 247, uint64_t{1} << 40), "holds only 50");
  ExpectRefused(good.substr(0, good.size() - 10), "holds only 49");
  ExpectRefused(With<double>(good, 131, 0.0), "X scale factor 0");
  ExpectRefused(With<double>(good, 163, std::nan("")), "Y offset");
  // Extra bytes descriptions that do not fit the records, or name no known type.
  auto extra = ReadFileBytes(kData + "extra_1_4_format8.las");
  ASSERT_TRUE(extra.ok()) << extra.status();
  const size_t fields = extra->find("LASF_Spec") - 2 + 54;  // The record's header starts 2 bytes before its user.
  ExpectRefused(With<uint8_t>(*extra, fields + 2, 31), "extra bytes field 0 has data type 31");
  ExpectRefused(With<uint8_t>(*extra, fields + 2 * 192 + 3, 3), "take more than the 6 bytes");
  ExpectRefused(With<double>(*extra, fields + 112, std::nan("")), "Amplitude has a scale or offset");
  // A box that lies does not move the points by it, nor refuse them.
  auto lied = ParseLas(With<double>(good, 179, 1e300), "box.las");
  EXPECT_TRUE(lied.ok()) << lied.status();
}

}  // namespace
}  // namespace lsqsurf::io
