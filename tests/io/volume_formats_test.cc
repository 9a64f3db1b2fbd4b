#include "worker/io/volume_formats.h"

#include <gtest/gtest.h>
#include <sys/resource.h>

#include <cmath>
#include <fstream>
#include <sstream>

#include "tests/zlib_bomb.h"
#include "worker/io/files.h"
#include "worker/io/volume_codec.h"
#include "worker/volume/synthetic.h"

namespace lsqsurf::io {
namespace {

constexpr uint64_t kNoInflateLimit = UINT64_MAX;

using volume::VolumeMesh;

VolumeMesh MixedMesh() {
  VolumeMesh m = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 4, 0.2, 3);
  // A hexahedron, a wedge and a pyramid on top of the tetrahedra, sharing no vertex.
  const uint32_t base = static_cast<uint32_t>(m.positions.size());
  for (const core::Vec3f& p : std::vector<core::Vec3f>{
           {2, 0, 0}, {3, 0, 0}, {3, 1, 0}, {2, 1, 0}, {2, 0, 1}, {3, 0, 1}, {3, 1, 1}, {2, 1, 1}, {2.5f, 0.5f, 2}}) {
    m.positions.push_back(p);
  }
  const std::array<uint32_t, 8> hex = {base, base + 1, base + 2, base + 3, base + 4, base + 5, base + 6, base + 7};
  m.AddCell(volume::CellType::kHexahedron, hex);
  const std::array<uint32_t, 5> pyramid = {base + 4, base + 5, base + 6, base + 7, base + 8};
  m.AddCell(volume::CellType::kPyramid, pyramid);
  const std::array<uint32_t, 6> wedge = {base, base + 2, base + 1, base + 4, base + 6, base + 5};
  m.AddCell(volume::CellType::kWedge, wedge);
  volume::SampleField(m, volume::Franke3d());
  volume::VertexField velocity{"velocity", 3, {}};
  for (const core::Vec3f& p : m.positions) velocity.values.insert(velocity.values.end(), {p.y(), -p.x(), 0.5f});
  m.fields.push_back(velocity);
  return m;
}

void ExpectSameMesh(const VolumeMesh& a, const VolumeMesh& b, float tolerance) {
  ASSERT_EQ(a.vertex_count(), b.vertex_count());
  for (size_t i = 0; i < a.vertex_count(); ++i) EXPECT_LE((a.positions[i] - b.positions[i]).norm(), tolerance);
  EXPECT_EQ(a.cell_types, b.cell_types);
  EXPECT_EQ(a.cell_offsets, b.cell_offsets);
  EXPECT_EQ(a.cell_vertices, b.cell_vertices);
}

TEST(LegacyVtk, UnstructuredGridRoundTripsInAsciiAndBinary) {
  const VolumeMesh mesh = MixedMesh();
  for (bool binary : {false, true}) {
    auto back = ParseLegacyVtk(EncodeLegacyVtk(mesh, binary), "mem.vtk");
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectSameMesh(mesh, *back, binary ? 0 : 1e-6f);
    ASSERT_EQ(back->fields.size(), 2u);
    EXPECT_EQ(back->fields[0].name, "franke");
    EXPECT_EQ(back->fields[1].name, "velocity");
    EXPECT_EQ(back->fields[1].components, 3);
    for (size_t i = 0; i < mesh.fields[0].values.size(); ++i) {
      EXPECT_NEAR(back->fields[0].values[i], mesh.fields[0].values[i], 1e-6);
    }
  }
}

TEST(LegacyVtk, ReadsStructuredPointsRectilinearCurvilinearAndVersion5) {
  const std::string points =
      "# vtk DataFile Version 3.0\nbox\nASCII\nDATASET STRUCTURED_POINTS\nDIMENSIONS 2 2 2\nORIGIN 1 2 3\n"
      "SPACING 0.5 1 2\nPOINT_DATA 8\nSCALARS density float 1\nLOOKUP_TABLE default\n0 1 2 3 4 5 6 7\n";
  auto sp = ParseLegacyVtk(points, "sp.vtk");
  ASSERT_TRUE(sp.ok()) << sp.status();
  EXPECT_EQ(sp->cell_count(), 1u);
  EXPECT_TRUE(sp->positions[7].isApprox(core::Vec3f(1.5f, 3, 5)));
  EXPECT_EQ(sp->fields[0].values[5], 5);

  const std::string rect =
      "# vtk DataFile Version 3.0\nr\nASCII\nDATASET RECTILINEAR_GRID\nDIMENSIONS 3 2 2\nX_COORDINATES 3 float\n0 1 "
      "3\nY_COORDINATES 2 float\n0 1\nZ_COORDINATES 2 double\n0 5\nPOINT_DATA 12\nFIELD FieldData 1\nt 1 12 float\n"
      "0 1 2 3 4 5 6 7 8 9 10 11\n";
  auto rg = ParseLegacyVtk(rect, "r.vtk");
  ASSERT_TRUE(rg.ok()) << rg.status();
  EXPECT_EQ(rg->cell_count(), 2u);
  EXPECT_TRUE(rg->positions[11].isApprox(core::Vec3f(3, 1, 5)));
  EXPECT_EQ(rg->fields[0].name, "t");

  const std::string curvi =
      "# vtk DataFile Version 3.0\nc\nASCII\nDATASET STRUCTURED_GRID\nDIMENSIONS 2 2 2\nPOINTS 8 float\n"
      "0 0 0 1 0 0 0 1 0 1.2 1 0 0 0 1 1 0 1 0 1 1 1 1 1.3\nPOINT_DATA 8\nVECTORS v float\n"
      "0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0\n";
  auto sg = ParseLegacyVtk(curvi, "c.vtk");
  ASSERT_TRUE(sg.ok()) << sg.status();
  EXPECT_EQ(sg->cell_count(), 1u);
  EXPECT_EQ(sg->fields[0].components, 3);

  const std::string v5 =
      "# vtk DataFile Version 5.1\nv5\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 4 float\n0 0 0 1 0 0 0 1 0 0 0 1\n"
      "CELLS 2 4\nOFFSETS vtktypeint64\n0 4\nCONNECTIVITY vtktypeint64\n0 1 2 3\nCELL_TYPES 1\n10\n"
      "CELL_DATA 1\nSCALARS id int 1\nLOOKUP_TABLE default\n7\nPOINT_DATA 4\nSCALARS f double\nLOOKUP_TABLE default\n"
      "1 2 3 4\n";
  auto u5 = ParseLegacyVtk(v5, "v5.vtk");
  ASSERT_TRUE(u5.ok()) << u5.status();
  EXPECT_EQ(u5->cell_count(), 1u);
  ASSERT_EQ(u5->fields.size(), 1u);  // The cell array is skipped.
  EXPECT_EQ(u5->fields[0].values[3], 4);
}

std::string Refusal(const std::string& text) {
  auto r = ParseLegacyVtk(text, "bad.vtk");
  return r.ok() ? "" : std::string(r.status().message());
}

TEST(LegacyVtk, RefusesHostileFilesWithAReason) {
  const std::string head =
      "# vtk DataFile Version 3.0\nx\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 4 float\n"
      "0 0 0 1 0 0 0 1 0 0 0 1\n";
  EXPECT_NE(Refusal("hello").find("not a legacy VTK file"), std::string::npos);
  EXPECT_NE(Refusal(head + "CELLS 1 4\n3 0 1 2\nCELL_TYPES 1\n5\n").find("triangle"), std::string::npos);
  EXPECT_NE(Refusal(head + "CELLS 1 5\n4 0 1 2 9\nCELL_TYPES 1\n10\n").find("vertex 9"), std::string::npos);
  // Cells in the mirrored order and missing values (NaN) are read as they are: they have a
  // reading, which core::RepairVolumeMesh gives them.
  EXPECT_EQ(Refusal(head + "CELLS 1 5\n4 0 2 1 3\nCELL_TYPES 1\n10\n"), "");
  EXPECT_EQ(Refusal(head + "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n10\nPOINT_DATA 4\nSCALARS f float\n"
                           "LOOKUP_TABLE default\n1 nan 3 4\n"),
            "");
  EXPECT_NE(
      Refusal(head + "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n24\n").find("quadratic tetrahedron) has 4 vertices, not 10"),
      std::string::npos);
  EXPECT_NE(Refusal(head + "CELLS 1 5000000\n4 0 1 2 3\n").find("do not fit"), std::string::npos);
  // Counts are bounded before they are multiplied (a lookup table's size × 4 overflowed).
  EXPECT_NE(Refusal(head + "CELLS 1 5000000000\n4 0 1 2 3\n").find("too large"), std::string::npos);
  EXPECT_NE(Refusal(head + "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n10\nPOINT_DATA 4\nSCALARS f float\n"
                           "LOOKUP_TABLE default\n1 2 3 4\nLOOKUP_TABLE t 2666666666666666661\n")
                .find("too large"),
            std::string::npos);
  EXPECT_NE(Refusal("# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\n").find("holds no volume"),
            std::string::npos);
  const std::string binary = EncodeLegacyVtk(MixedMesh(), true);
  EXPECT_NE(Refusal(binary.substr(0, binary.size() / 2)).find("truncated"), std::string::npos)
      << Refusal(binary.substr(0, binary.size() / 2));
}

TEST(RawVolume, ReadsTheBuckyBallLayout) {
  std::string bytes(4 * 3 * 2, '\0');
  for (size_t i = 0; i < bytes.size(); ++i) bytes[i] = static_cast<char>(i * 10);
  auto m = ParseRawVolume(bytes, "4x3x2:uint8:0.5,1,2", "density");
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->vertex_count(), 24u);
  EXPECT_EQ(m->cell_count(), 3u * 2 * 1);
  EXPECT_TRUE(m->positions[23].isApprox(core::Vec3f(1.5f, 2, 2)));
  EXPECT_EQ(m->fields[0].values[23], 230);
  EXPECT_FALSE(ParseRawVolume(bytes, "4x3x3:uint8", "d").ok());
  EXPECT_FALSE(ParseRawVolume(bytes, "4x3:uint8", "d").ok());
  EXPECT_FALSE(ParseRawVolume(bytes, "4x3x2:complex", "d").ok());
  auto f32 = ParseRawVolume(std::string(4 * 24, '\0'), "4x3x2:float32", "d");
  EXPECT_TRUE(f32.ok()) << f32.status();
}

TEST(PlyVolume, PointsWithValues) {
  const std::string ply =
      "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nproperty float temperature\nend_header\n0 0 0 1.5\n1 0 0 2.5\n0 1 0 3.5\n";
  auto m = ParsePlyVolume(ply, "p.ply");
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_FALSE(m->has_cells());
  EXPECT_EQ(m->fields[0].name, "temperature");
  EXPECT_EQ(m->fields[0].values[2], 3.5f);
}

TEST(VolumeCodec, VerticesAndCellsRoundTripSmallerThanBinaryVtk) {
  VolumeMesh mesh = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 21, 0.3, 3);
  volume::SampleField(mesh, volume::Franke3d());
  const std::vector<std::string> fields = {"franke"};
  auto vertices = EncodeVolumeVertices(mesh, fields, {});
  ASSERT_TRUE(vertices.ok()) << vertices.status();
  const std::string cells = EncodeCellStream(mesh);
  VolumeMesh back;
  ASSERT_TRUE(DecodeVolumeVertices(*vertices, back).ok());
  ASSERT_TRUE(DecodeCellStream(cells, 1'000'000, kNoInflateLimit, back).ok());
  ExpectSameMesh(mesh, back, 2e-6f);  // 20-bit positions over a unit box.
  ASSERT_EQ(back.fields.size(), 1u);
  for (size_t i = 0; i < mesh.vertex_count(); ++i)
    EXPECT_NEAR(back.fields[0].values[i], mesh.fields[0].values[i], 2e-6);
  const size_t vtk = EncodeLegacyVtk(mesh, true).size();
  std::printf("upload %zu + %zu bytes vs binary vtk %zu\n", vertices->size(), cells.size(), vtk);
  EXPECT_LT(vertices->size() + cells.size(), vtk / 3);
  // Limits and corruption.
  VolumeMesh sink;
  EXPECT_EQ(DecodeCellStream(cells, 10, kNoInflateLimit, sink).code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(DecodeCellStream(cells.substr(0, cells.size() / 2), 1'000'000, kNoInflateLimit, sink).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(DecodeCellStream("LQC0", 10, kNoInflateLimit, sink).code(), absl::StatusCode::kInvalidArgument);
}

// The peak resident memory of this process, bytes.
int64_t PeakResidentBytes() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return int64_t{usage.ru_maxrss} * 1024;
}

TEST(VolumeCodec, ADeclaredLengthIsNeverAllocatedBeforeItsBytesInflate) {
  // 17 bytes: the magic, a payload length of 4.1e9 and an empty zlib stream. The length is within
  // what 100M cells could need, so only the bytes behind it can refuse it.
  std::string lying = "LQC1";
  uint64_t declared = 4'100'000'000;
  for (; declared >= 0x80; declared >>= 7) lying += static_cast<char>((declared & 0x7f) | 0x80);
  lying += static_cast<char>(declared);
  lying += std::string("\x78\x9c\x03\x00\x00\x00\x00\x01", 8);
  ASSERT_EQ(lying.size(), 17u);
  const int64_t peak_before = PeakResidentBytes();
  VolumeMesh sink;
  const absl::Status refused = DecodeCellStream(lying, 100'000'000, kNoInflateLimit, sink);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
  EXPECT_NE(refused.message().find("compressed bytes can hold"), std::string_view::npos) << refused;
  // A length that its bytes could hold, with a stream that inflates to far less: refused as well.
  const std::string cells =
      EncodeCellStream(volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 4, 0.2, 3));
  std::string longer = "LQC1";
  uint64_t size = 0, shift = 0;
  size_t pos = 4;
  for (;; shift += 7) {
    const auto byte = static_cast<uint8_t>(cells[pos++]);
    size |= uint64_t{byte & 0x7fu} << shift;
    if ((byte & 0x80) == 0) break;
  }
  uint64_t claimed = (cells.size() - pos) * 1000;
  ASSERT_GT(claimed, size);
  for (; claimed >= 0x80; claimed >>= 7) longer += static_cast<char>((claimed & 0x7f) | 0x80);
  longer += static_cast<char>(claimed);
  longer += cells.substr(pos);
  const absl::Status short_stream = DecodeCellStream(longer, 100'000'000, kNoInflateLimit, sink);
  EXPECT_EQ(short_stream.code(), absl::StatusCode::kInvalidArgument) << short_stream;
  EXPECT_NE(short_stream.message().find("inflates to"), std::string_view::npos) << short_stream;
  // Neither grew the process by the declared sizes (the old decoder zeroed all 4.1 GB first).
  EXPECT_LT(PeakResidentBytes() - peak_before, int64_t{256} << 20);
}

// A real bomb: one tetrahedron, then 512 MiB of zeros, 0.5 MB compressed, its length declared
// truly. Parsed as it inflates, it is refused at the first byte past the cell, holding a window;
// a caller's inflation limit stops a stream that is well-formed throughout.
TEST(VolumeCodec, AStreamThatInflatesAThousandfoldCostsItsWindowOnly) {
  const std::string bomb = testing::CellStreamBomb(uint64_t{512} << 20);
  ASSERT_LT(bomb.size(), size_t{1} << 20);
  const int64_t peak_before = PeakResidentBytes();
  VolumeMesh sink;
  const absl::Status refused = DecodeCellStream(bomb, 100'000'000, kNoInflateLimit, sink);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
  EXPECT_NE(refused.message().find("bytes follow the last cell"), std::string_view::npos) << refused;
  EXPECT_LT(PeakResidentBytes() - peak_before, int64_t{64} << 20);

  const VolumeMesh mesh = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 9, 0.2, 3);
  const std::string cells = EncodeCellStream(mesh);
  VolumeMesh back;
  EXPECT_TRUE(DecodeCellStream(cells, 1'000'000, 1 << 20, back).ok());
  EXPECT_EQ(back.cell_count(), mesh.cell_count());
  const absl::Status over = DecodeCellStream(cells, 1'000'000, 4096, back);
  EXPECT_EQ(over.code(), absl::StatusCode::kResourceExhausted) << over;
  EXPECT_NE(over.message().find("--max-upload-mib"), std::string_view::npos) << over;
}

}  // namespace
}  // namespace lsqsurf::io

namespace lsqsurf::io {
namespace {

// Files written by VTK 9.1's own writers (tests/data/volume/make_fixtures.py): a hexahedron, a
// pyramid, a tetrahedron and a wedge; temperature = 1 + x + 2y + 3z, velocity = (y, -x, z).
void ExpectTheFixture(const std::string& file) {
  SCOPED_TRACE(file);
  auto mesh = ReadVolumeFile(std::string(LSQSURF_SOURCE_DIR "/tests/data/volume/") + file);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_EQ(mesh->vertex_count(), 15u);
  EXPECT_EQ(mesh->cell_types, (std::vector<uint8_t>{12, 14, 10, 13}));
  const volume::VertexField* t = mesh->FindField("temperature");
  const volume::VertexField* v = mesh->FindField("velocity");
  ASSERT_NE(t, nullptr);
  ASSERT_NE(v, nullptr);
  EXPECT_EQ(v->components, 3);
  for (size_t i = 0; i < mesh->vertex_count(); ++i) {
    const core::Vec3f& p = mesh->positions[i];
    EXPECT_NEAR(t->values[i], 1 + p.x() + 2 * p.y() + 3 * p.z(), 1e-5);
    EXPECT_NEAR(v->values[3 * i], p.y(), 1e-6);
    EXPECT_NEAR(v->values[3 * i + 1], -p.x(), 1e-6);
  }
  EXPECT_EQ(mesh->cell(3)[0], 9u);  // The wedge, in VTK's order.
}

TEST(Vtu, ReadsEveryEncodingVtkWrites) {
  for (const char* file : {"mixed-ascii.vtu", "mixed-binary.vtu", "mixed-binary-zlib.vtu", "mixed-appended-zlib.vtu",
                           "mixed-appended-base64.vtu", "mixed-binary.vtk"}) {
    ExpectTheFixture(file);
  }
}

TEST(Vtu, RefusesDamagedFilesWithAReason) {
  auto bytes = ReadFileBytes(LSQSURF_SOURCE_DIR "/tests/data/volume/mixed-appended-zlib.vtu");
  ASSERT_TRUE(bytes.ok());
  // Every truncation that loses data fails cleanly (no crash, no read past the end).
  const size_t data_end = bytes->rfind("</AppendedData>");
  for (size_t cut = 0; cut < data_end; cut += 97) {
    auto r = ParseVtu(bytes->substr(0, cut), "cut.vtu");
    EXPECT_FALSE(r.ok()) << cut;
  }
  std::string flipped = *bytes;
  flipped[flipped.size() - 40] ^= 0x5a;  // Inside the last compressed block.
  EXPECT_FALSE(ParseVtu(flipped, "flipped.vtu").ok());
  auto ascii = ReadFileBytes(LSQSURF_SOURCE_DIR "/tests/data/volume/mixed-ascii.vtu");
  ASSERT_TRUE(ascii.ok());
  std::string polydata = *ascii;
  polydata.replace(polydata.find("UnstructuredGrid"), 16, "PolyData");
  EXPECT_NE(std::string(ParseVtu(polydata, "p.vtu").status().message()).find("not UnstructuredGrid"),
            std::string::npos);
  std::string bad_type = *ascii;
  bad_type.replace(bad_type.find("          12 14 10 13"), 21, "          5 14 10 13");
  EXPECT_NE(std::string(ParseVtu(bad_type, "t.vtu").status().message()).find("triangle"), std::string::npos)
      << ParseVtu(bad_type, "t.vtu").status();
}

}  // namespace
}  // namespace lsqsurf::io
