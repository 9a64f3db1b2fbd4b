// PTS and PTX: scanner exports laid out by hand as Leica's software writes them (count lines,
// intensity before colour, a scan header whose matrix turns and moves the scan, missing pixels
// at 0 0 0), round trips through the PTX writer with several stations, streaming, and broken
// files.
#include "worker/io/pts_ptx.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>

#include "tests/test_dir.h"
#include "worker/io/files.h"
#include "worker/io/point_stream.h"

namespace lsqsurf::io {
namespace {

const core::ScalarAttribute* Find(const core::PointCloud& cloud, const std::string& name) {
  for (const auto& a : cloud.attributes) {
    if (a.name == name) return &a;
  }
  return nullptr;
}

TEST(Pts, ReadsCountLinesIntensityAndColour) {
  // Two scans concatenated, each with its count; intensity (Leica's -2048..2047) before colour.
  const std::string text =
      "3\n1.5 2 3 -1200 10 20 30\n4 5 6 0 40 50 60\r\n7 8 9 2047 70 80 90\n\n2\n-1 -2 -3 5 1 2 3\n0 0 0 6 4 5 6\n";
  auto cloud = ParsePts(text, "scan.pts");
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  ASSERT_EQ(cloud->size(), 5u);
  EXPECT_EQ(cloud->positions[0], core::Vec3f(1.5f, 2, 3));
  EXPECT_EQ(cloud->positions[4], core::Vec3f(0, 0, 0));  // PTS has no missing-pixel rule.
  const auto* intensity = Find(*cloud, "intensity");
  ASSERT_NE(intensity, nullptr);
  EXPECT_EQ(intensity->values, (std::vector<float>{-1200, 0, 2047, 5, 6}));
  const auto channels = core::ColourChannels(cloud->attributes, cloud->size());
  ASSERT_NE(channels[0], nullptr);
  EXPECT_EQ(channels[0]->values, (std::vector<float>{10, 40, 70, 1, 4}));
  EXPECT_EQ(channels[2]->values, (std::vector<float>{30, 60, 90, 3, 6}));

  auto plain = ParsePts("1 2 3\n4 5 6\n", "plain.pts");
  ASSERT_TRUE(plain.ok());
  EXPECT_TRUE(plain->attributes.empty());
  auto grey = ParsePts("1 2 3 9\n", "grey.pts");
  ASSERT_TRUE(grey.ok());
  ASSERT_EQ(grey->attributes.size(), 1u);
  EXPECT_EQ(grey->attributes[0].name, "intensity");
}

void ExpectRefused(const absl::Status& status, const std::string& words) {
  ASSERT_FALSE(status.ok()) << words;
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find(words), std::string::npos) << status;
}

TEST(Pts, BrokenFilesAreRefusedWithTheLine) {
  ExpectRefused(ParsePts("1 2 3\n4 5 6 7\n", "a.pts").status(), "a.pts:2: expected 3 values");
  ExpectRefused(ParsePts("1 2\n", "b.pts").status(), "b.pts:1: expected x y z");
  ExpectRefused(ParsePts("1 2 x\n", "c.pts").status(), "not a number");
  ExpectRefused(ParsePts("1 2 3 4 5 6 7 8\n", "d.pts").status(), "more than 7 values");
  ExpectRefused(ParsePts("5\n\n", "e.pts").status(), "no points");
}

// A scan header for PTX: grid, position, axes, and the matrix rows.
std::string Header(int columns, int rows, const std::string& position, const std::string& matrix) {
  return std::to_string(columns) + "\n" + std::to_string(rows) + "\n" + position + "\n1 0 0\n0 1 0\n0 0 1\n" + matrix;
}

TEST(Ptx, TurnsAndMovesEachScanAndSkipsMissingPixels) {
  // A scanner at (10, 20, 1), turned 90° about z: its x axis is the registered y. [p 1]·M puts
  // the local (1, 0, 0) at (10, 21, 1) and (0, 2, 0) at (8, 20, 1).
  const std::string turned = "0 1 0 0\n-1 0 0 0\n0 0 1 0\n10 20 1 1\n";
  const std::string text = Header(2, 2, "10 20 1", turned) +
                           "1 0 0 0.5 255 0 0\n0 0 0 0.5 0 0 0\n0 2 0 0.25 0 255 0\n0 0 3 0.75 0 0 255\n" +
                           Header(1, 1, "-5 0 0", "1 0 0 0\n0 1 0 0\n0 0 1 0\n-5 0 0 1\n") + "1 1 1 0.1 9 9 9\n";
  PtxInfo info;
  auto cloud = ParsePtx(text, "two.ptx", &info);
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  ASSERT_EQ(info.stations.size(), 2u);
  EXPECT_EQ(info.stations[0], core::Vec3d(10, 20, 1));
  EXPECT_EQ(info.stations[1], core::Vec3d(-5, 0, 0));
  EXPECT_EQ(info.points, 5u);
  EXPECT_EQ(info.skipped_points, 1u);
  ASSERT_EQ(cloud->size(), 4u);
  EXPECT_NEAR((cloud->positions[0] - core::Vec3f(10, 21, 1)).norm(), 0, 1e-6);
  EXPECT_NEAR((cloud->positions[1] - core::Vec3f(8, 20, 1)).norm(), 0, 1e-6);
  EXPECT_NEAR((cloud->positions[2] - core::Vec3f(10, 20, 4)).norm(), 0, 1e-6);
  EXPECT_NEAR((cloud->positions[3] - core::Vec3f(-4, 1, 1)).norm(), 0, 1e-6);
  const auto* scan = Find(*cloud, "scan");
  ASSERT_NE(scan, nullptr);
  EXPECT_EQ(scan->values, (std::vector<float>{0, 0, 0, 1}));
  const auto* intensity = Find(*cloud, "intensity");
  ASSERT_NE(intensity, nullptr);
  EXPECT_EQ(intensity->values, (std::vector<float>{0.5f, 0.25f, 0.75f, 0.1f}));
  const auto channels = core::ColourChannels(cloud->attributes, cloud->size());
  ASSERT_NE(channels[1], nullptr);
  EXPECT_EQ(channels[1]->values, (std::vector<float>{0, 255, 0, 9}));
}

TEST(Ptx, RoundTripsSeveralStationsAndStreamsThem) {
  core::PointCloud a, b;
  for (int i = 0; i < 60; ++i) {
    const auto t = static_cast<float>(i);
    a.positions.emplace_back(std::cos(0.1f * t), std::sin(0.1f * t), 0.5f);
    b.positions.emplace_back(2.0f + 0.01f * t, -1.0f, 0.02f * t);
  }
  const std::vector<PtxScan> scans = {{core::Vec3d(0, 0, 2), &a, 6, 10}, {core::Vec3d(3, -4, 1), &b}};
  const std::filesystem::path dir = testing::FreshTestDir("lsqsurf-ptx");
  std::filesystem::create_directories(dir);
  const std::string path = (dir / "stations.ptx").string();
  ASSERT_TRUE(WriteFileAtomically(path, EncodePtx(scans)).ok());
  auto stream = OpenPointStream(path);
  ASSERT_TRUE(stream.ok()) << stream.status();
  ASSERT_EQ((*stream)->sensor_positions().size(), 2u);
  EXPECT_EQ((*stream)->sensor_positions()[1], core::Vec3d(3, -4, 1));
  core::PointCloud streamed;
  std::vector<float> scan;
  for (;;) {
    auto chunk = (*stream)->Next(7);
    ASSERT_TRUE(chunk.ok()) << chunk.status();
    if (chunk->size() == 0) break;
    streamed.positions.insert(streamed.positions.end(), chunk->positions.begin(), chunk->positions.end());
    const auto* s = Find(*chunk, "scan");
    ASSERT_NE(s, nullptr);
    scan.insert(scan.end(), s->values.begin(), s->values.end());
  }
  ASSERT_EQ(streamed.size(), 120u);
  for (int i = 0; i < 60; ++i) {
    EXPECT_NEAR((streamed.positions[i] - a.positions[i]).norm(), 0, 1e-6);
    EXPECT_NEAR((streamed.positions[60 + i] - b.positions[i]).norm(), 0, 1e-6);
    EXPECT_EQ(scan[i], 0.0f);
    EXPECT_EQ(scan[60 + i], 1.0f);
  }
  std::filesystem::remove_all(dir);
}

TEST(Ptx, ScansOfPositionsAloneCarryOnlyTheirScan) {
  const std::string identity = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n";
  auto cloud =
      ParsePtx(Header(1, 1, "0 0 0", identity) + "1 2 3\n" + Header(1, 1, "0 0 0", identity) + "4 5 6\n", "bare.ptx");
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  ASSERT_EQ(cloud->attributes.size(), 1u);
  EXPECT_EQ(cloud->attributes[0].name, "scan");
  EXPECT_EQ(cloud->attributes[0].values, (std::vector<float>{0, 1}));
}

TEST(Ptx, BrokenFilesAreRefusedBeforeAPointIsHandedOut) {
  const std::string identity = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n";
  ExpectRefused(PtxReader::Open(Header(2, 2, "0 0 0", identity) + "1 1 1 0.5\n", "short.ptx").status(),
                "scan 1 ends after 1 of its 4 points");
  ExpectRefused(PtxReader::Open("3\n2\n0 0 0\n1 0 0\n", "cut.ptx").status(), "header ends");
  ExpectRefused(PtxReader::Open(Header(1, 1, "0 0", identity) + "1 1 1 1\n", "pos.ptx").status(),
                "pos.ptx:3: expected 3 numbers (the scanner's position)");
  ExpectRefused(PtxReader::Open("99999999999\n1\n", "huge.ptx").status(), "expected the scan's columns");
  ExpectRefused(PtxReader::Open("", "empty.ptx").status(), "no scans");
  auto odd = ParsePtx(Header(1, 2, "0 0 0", identity) + "1 1 1 1\n1 1\n", "odd.ptx");
  ExpectRefused(odd.status(), "odd.ptx:12: expected x y z intensity");
}

}  // namespace
}  // namespace lsqsurf::io
