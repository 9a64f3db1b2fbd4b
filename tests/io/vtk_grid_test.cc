#include "worker/io/vtk_grid.h"

#include <gtest/gtest.h>

#include <string>

namespace lsqsurf::io {
namespace {

using core::Vec3d;

// A 2×1×2 grid as ParaView's legacy writer lays it out (values split across lines).
constexpr char kAscii[] =
    "# vtk DataFile Version 3.0\n"
    "a hand-written field\n"
    "ASCII\n"
    "DATASET STRUCTURED_POINTS\n"
    "DIMENSIONS 2 1 2\n"
    "SPACING 0.5 1 0.25\n"
    "ORIGIN -1 0 2\n"
    "POINT_DATA 4\n"
    "VECTORS v float\n"
    "1 2 3 4 5 6\n"
    "7 8 9\n"
    "-1e-3 0 1.5\n";

TEST(VtkGrid, ParsesAsciiInXFastestOrder) {
  auto grid = ParseVtkVectorGrid(kAscii, "ascii.vtk");
  ASSERT_TRUE(grid.ok()) << grid.status();
  EXPECT_EQ(grid->dims, (std::array<int, 3>{2, 1, 2}));
  EXPECT_EQ(grid->origin, Vec3d(-1, 0, 2));
  EXPECT_EQ(grid->spacing, Vec3d(0.5, 1, 0.25));
  ASSERT_EQ(grid->values.size(), 4u);
  EXPECT_EQ(grid->values[1], Vec3d(4, 5, 6));
  EXPECT_EQ(grid->values[3], Vec3d(-1e-3, 0, 1.5));
}

TEST(VtkGrid, ParsesBigEndianBinary) {
  // 1.0f is 3F 80 00 00 and -2.0f is C0 00 00 00 in big-endian IEEE 754.
  std::string file =
      "# vtk DataFile Version 3.0\nb\nBINARY\nDATASET STRUCTURED_POINTS\nDIMENSIONS 1 1 1\n"
      "POINT_DATA 1\nVECTORS v float\n";
  file += std::string("\x3F\x80\x00\x00", 4) + std::string("\xC0\x00\x00\x00", 4) + std::string(4, '\0');
  auto grid = ParseVtkVectorGrid(file, "binary.vtk");
  ASSERT_TRUE(grid.ok()) << grid.status();
  EXPECT_EQ(grid->values[0], Vec3d(1, -2, 0));
  EXPECT_EQ(grid->origin, Vec3d::Zero());
  EXPECT_EQ(grid->spacing, Vec3d::Ones());
}

TEST(VtkGrid, EncodeRoundTripsBothModes) {
  VectorGrid grid;
  grid.dims = {3, 2, 2};
  grid.origin = Vec3d(0.125, -0.5, 0);
  grid.spacing = Vec3d(0.25, 0.5, 1);
  for (int i = 0; i < 12; ++i) grid.values.emplace_back(i * 0.5, -i, 1.0 / (i + 1));
  for (bool binary : {false, true}) {
    auto back = ParseVtkVectorGrid(EncodeVtkVectorGrid(grid, binary), "round trip");
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(back->dims, grid.dims);
    EXPECT_EQ(back->origin, grid.origin);
    EXPECT_EQ(back->spacing, grid.spacing);
    for (size_t i = 0; i < grid.values.size(); ++i) {
      EXPECT_NEAR((back->values[i] - grid.values[i]).norm(), 0, 1e-7) << i;  // Stored as float.
    }
  }
}

TEST(VtkGrid, RefusesMalformedFilesWithTheLine) {
  const std::string ascii = kAscii;
  auto expect_error = [](const std::string& file, const std::string& fragment) {
    auto grid = ParseVtkVectorGrid(file, "f.vtk");
    ASSERT_EQ(grid.status().code(), absl::StatusCode::kInvalidArgument) << fragment;
    EXPECT_NE(grid.status().message().find(fragment), std::string::npos) << grid.status();
  };
  expect_error("P3\n2 2\n", "not a legacy VTK file");
  expect_error(ascii.substr(0, ascii.size() - 4), "truncated");
  std::string unstructured = ascii;
  unstructured.replace(unstructured.find("STRUCTURED_POINTS"), 17, "UNSTRUCTURED_GRID");
  expect_error(unstructured, "STRUCTURED_POINTS");
  std::string count = ascii;
  count.replace(count.find("POINT_DATA 4"), 12, "POINT_DATA 5");
  expect_error(count, "must equal nx·ny·nz = 4");
  std::string nan = ascii;
  nan.replace(nan.find("7 8 9"), 5, "7 nan 9");
  expect_error(nan, "not");
  std::string spacing = ascii;
  spacing.replace(spacing.find("SPACING 0.5"), 11, "SPACING 0.0");
  expect_error(spacing, "SPACING positive");
  std::string huge = ascii;
  huge.replace(huge.find("DIMENSIONS 2 1 2"), 16, "DIMENSIONS 1000 1000 1000");
  expect_error(huge, "at most");
  std::string binary =
      "# vtk DataFile Version 3.0\nb\nBINARY\nDATASET STRUCTURED_POINTS\nDIMENSIONS 2 1 1\n"
      "POINT_DATA 2\nVECTORS v double\n" +
      std::string(40, '\0');
  expect_error(binary, "truncated");
  std::string scalars_only = ascii;
  scalars_only.replace(scalars_only.find("VECTORS v float"), 15, "SCALARS s float 3\nLOOKUP_TABLE default");
  expect_error(scalars_only, "no VECTORS");
}

// What the volume reader takes, a velocity grid takes too: scalars before the vectors, cell
// data, a VTK 5 header; the first VECTORS array is the field.
TEST(VtkGrid, ReadsWhatTheVolumeReaderReads) {
  const std::string file =
      "# vtk DataFile Version 5.1\nexported\nASCII\nDATASET STRUCTURED_POINTS\nORIGIN 0 0 0\n"
      "DIMENSIONS 2 1 1\nSPACING 1 1 1\nCELL_DATA 1\nSCALARS c int 1\nLOOKUP_TABLE default\n7\n"
      "POINT_DATA 2\nSCALARS p double 1\nLOOKUP_TABLE default\n0.5 0.25\nVECTORS u double\n"
      "0.1 0.2 0.3 -1 -2 -3\nVECTORS w float\n9 9 9 9 9 9\n";
  auto grid = ParseVtkVectorGrid(file, "exported.vtk");
  ASSERT_TRUE(grid.ok()) << grid.status();
  EXPECT_EQ(grid->values[0], Vec3d(0.1, 0.2, 0.3));  // Doubles stay doubles.
  EXPECT_EQ(grid->values[1], Vec3d(-1, -2, -3));
}

}  // namespace
}  // namespace lsqsurf::io
