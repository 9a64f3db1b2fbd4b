// Volume meshes as exporters write them: the repair gives back the mesh a careful writer would
// have made, checked against that mesh and against analytic fields.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <map>
#include <random>

#include "tests/volume/build_field.h"
#include "worker/volume/synthetic.h"
#include "worker/volume/volume_field.h"
#include "worker/volume/volume_mesh.h"

namespace lsqsurf::volume {
namespace {

double TotalVolume(const VolumeMesh& mesh) {
  double total = 0;
  for (const auto& t : Tetrahedralize(mesh)) {
    total += TetVolume(mesh.positions[t[0]], mesh.positions[t[1]], mesh.positions[t[2]], mesh.positions[t[3]]);
  }
  return total;
}

double RmsError(const VolumeField& field, const AnalyticField& truth, int count) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> unit(0.1, 0.9);
  double sum = 0;
  for (int i = 0; i < count; ++i) {
    const Vec3d x = truth.domain.min() + Vec3d(unit(rng), unit(rng), unit(rng)).cwiseProduct(truth.domain.sizes());
    const double d = field.Evaluate(x, 0).value - truth.value(x);
    sum += d * d;
  }
  return std::sqrt(sum / count);
}

// What a mesh writer that is not careful hands over, and how much of each it did.
struct Mess {
  VolumeMesh mesh;
  int64_t flipped = 0, duplicated = 0, unused = 0, slivers = 0;
};

// Every third cell mirrored, the corners of every fifth cell given copies of their own (as a
// writer of blocks repeats the points on their interfaces), points in no cell, and flat
// tetrahedra on the z = 0 face (Delaunay's boundary slivers).
Mess AsAnExporterWritesIt(const VolumeMesh& clean) {
  Mess out{clean};
  VolumeMesh& m = out.mesh;
  for (size_t c = 0; c < m.cell_count(); ++c) {
    uint32_t* v = m.cell_vertices.data() + m.cell_offsets[c];
    if (c % 3 == 0) {
      std::swap(v[1], v[2]);
      ++out.flipped;
    }
    if (c % 5 == 0) {
      for (int k = 0; k < 4; ++k) {
        m.positions.push_back(m.positions[v[k]]);
        for (VertexField& f : m.fields) f.values.push_back(f.values[v[k]]);
        v[k] = static_cast<uint32_t>(m.positions.size() - 1);
        ++out.duplicated;
      }
    }
  }
  std::vector<uint32_t> floor;
  for (uint32_t i = 0; i < clean.vertex_count(); ++i) {
    if (clean.positions[i].z() == 0) floor.push_back(i);
  }
  for (size_t s = 0; s + 3 < floor.size() && out.slivers < 10; s += 7, ++out.slivers) {
    const std::array<uint32_t, 4> flat = {floor[s], floor[s + 1], floor[s + 2], floor[s + 3]};
    m.AddCell(CellType::kTetrahedron, flat);
  }
  for (int i = 0; i < 50; ++i) {
    m.positions.push_back(Vec3f(5.0f + static_cast<float>(i), 0, 0));
    for (VertexField& f : m.fields) f.values.push_back(-1.0f);
    ++out.unused;
  }
  return out;
}

TEST(VolumeRepair, AnExportersCopyOfAMeshComesBackAsTheMeshWithTheSameField) {
  const AnalyticField franke = Franke3d();
  VolumeMesh clean = JitteredTetMesh(franke.domain, 13, 0.3, 3);
  SampleField(clean, franke);
  Mess mess = AsAnExporterWritesIt(clean);
  EXPECT_FALSE(ValidateVolumeMesh(mess.mesh, {}).ok());
  auto repairs = RepairVolumeMesh(mess.mesh);
  ASSERT_TRUE(repairs.ok()) << repairs.status();
  EXPECT_TRUE(ValidateVolumeMesh(mess.mesh, {}).ok()) << ValidateVolumeMesh(mess.mesh, {});
  EXPECT_EQ(repairs->reoriented_cells, mess.flipped);
  EXPECT_EQ(repairs->merged_vertices, mess.duplicated);
  EXPECT_EQ(repairs->unused_vertices, mess.unused);
  EXPECT_EQ(repairs->degenerate_cells, mess.slivers);
  EXPECT_EQ(repairs->missing_vertices, 0);
  EXPECT_EQ(repairs->linearised_cells, 0);
  // The careful writer's mesh, vertex for vertex (a duplicate merges into the first of its copies).
  ASSERT_EQ(mess.mesh.positions, clean.positions);
  ASSERT_EQ(mess.mesh.cell_count(), clean.cell_count() + static_cast<size_t>(mess.slivers));
  EXPECT_NEAR(TotalVolume(mess.mesh), 1.0, 1e-5);
  auto repaired = Build(mess.mesh, "franke"), reference = Build(clean, "franke");
  ASSERT_TRUE(repaired && reference);
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> unit(0, 1);
  for (int i = 0; i < 200; ++i) {
    const Vec3d x(unit(rng), unit(rng), unit(rng));
    EXPECT_NEAR(repaired->Evaluate(x, 0).value, reference->Evaluate(x, 0).value, 1e-9) << x.transpose();
  }
}

TEST(VolumeRepair, MissingValuesAreFilledFromTheirNeighboursOrRefusedWithTheCount) {
  const AnalyticField franke = Franke3d();
  VolumeMesh clean = JitteredTetMesh(franke.domain, 13, 0.3, 3);
  SampleField(clean, franke);
  VolumeMesh holed = clean;
  std::vector<float>& values = holed.fields[0].values;
  int64_t holes = 0;
  for (size_t i = 7; i < values.size(); i += 41, ++holes) values[i] = std::nanf("");
  values[100] = INFINITY;
  ++holes;
  auto repairs = RepairVolumeMesh(holed);
  ASSERT_TRUE(repairs.ok()) << repairs.status();
  EXPECT_EQ(repairs->missing_vertices, holes);
  ASSERT_TRUE(ValidateVolumeMesh(holed, {}).ok());
  // A filled value is a weighted mean of neighbours a spacing away: off by about the field's
  // change over one spacing (Franke's gradient is below 3 here, the spacing 1/12).
  // Franke's bumps change by up to 0.3 over one spacing (1/12) of this mesh.
  double worst_fill = 0;
  for (size_t i = 7; i < values.size(); i += 41) {
    worst_fill = std::max(worst_fill, std::abs(double{holed.fields[0].values[i]} - clean.fields[0].values[i]));
  }
  const double with_holes = RmsError(*Build(holed, "franke"), franke, 2000);
  const double without = RmsError(*Build(clean, "franke"), franke, 2000);
  std::printf("Franke: largest filled-in error %.3g; field RMS clean %.3g, 2.5 %% of the values filled in %.3g\n",
              worst_fill, without, with_holes);
  EXPECT_LT(worst_fill, 0.05);
  EXPECT_LT(with_holes, 2 * without);

  // A quadratic field is filled in exactly wherever the neighbours have values all round.
  VolumeMesh quadratic = clean;
  auto q = [](const Vec3f& p) { return p.x() * p.x() + 2 * p.y() * p.z() - p.z() + 0.5f; };
  quadratic.fields = {{"q", 1, {}}};
  for (const Vec3f& p : quadratic.positions) quadratic.fields[0].values.push_back(q(p));
  for (size_t i = 7; i < quadratic.vertex_count(); i += 41) quadratic.fields[0].values[i] = std::nanf("");
  ASSERT_TRUE(RepairVolumeMesh(quadratic).ok());
  int interior = 0;
  for (size_t i = 7; i < quadratic.vertex_count(); i += 41) {
    const Vec3f& p = quadratic.positions[i];
    if (p.minCoeff() <= 0 || p.maxCoeff() >= 1) continue;  // A boundary vertex: a linear fit.
    EXPECT_NEAR(quadratic.fields[0].values[i], q(p), 1e-4) << i;
    ++interior;
  }
  EXPECT_GT(interior, 20);

  VolumeMesh mostly_missing = clean;
  for (size_t i = 3; i < mostly_missing.vertex_count(); ++i) mostly_missing.fields[0].values[i] = std::nanf("");
  auto refused = RepairVolumeMesh(mostly_missing);
  ASSERT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("at " + std::to_string(clean.vertex_count() - 3) + " of"),
            std::string_view::npos)
      << refused.status();
  EXPECT_NE(refused.status().message().find("the first: vertex 3"), std::string_view::npos) << refused.status();

  // A point set has no neighbours to fill from: its valueless points are left out.
  VolumeMesh points = ScatteredPoints(franke.domain, 500, 2);
  SampleField(points, franke);
  points.fields[0].values[10] = std::nanf("");
  auto dropped = RepairVolumeMesh(points);
  ASSERT_TRUE(dropped.ok()) << dropped.status();
  EXPECT_EQ(dropped->missing_vertices, 1);
  EXPECT_EQ(points.vertex_count(), 499u);
  EXPECT_TRUE(ValidateVolumeMesh(points, {}).ok());
}

// Most of a mesh without values, as one block filled from one side: ring by ring, each vertex
// once (each ring used to scan every vertex still missing), and never past the values the data
// hold (the one-sided fits, extrapolated ring after ring, reached infinity here).
TEST(VolumeRepair, ADeepMissingBlockIsFilledWithinTheData) {
  VolumeMesh mesh = JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d(4, 1, 1)), 48, 0.2, 7);
  auto linear = [](const Vec3f& p) { return 2 * p.x() - p.y() + 0.5f * p.z(); };
  mesh.fields = {{"linear", 1, {}}};
  int64_t holes = 0;
  float lo = INFINITY, hi = -INFINITY;
  for (const Vec3f& p : mesh.positions) {
    const bool missing = p.x() > 1.0f;
    mesh.fields[0].values.push_back(missing ? std::nanf("") : linear(p));
    holes += missing;
    if (!missing) {
      lo = std::min(lo, linear(p));
      hi = std::max(hi, linear(p));
    }
  }
  VolumeRepairParams params;
  params.max_missing_share = 0.9;
  const auto start = std::chrono::steady_clock::now();
  auto repairs = RepairVolumeMesh(mesh, params);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  ASSERT_TRUE(repairs.ok()) << repairs.status();
  EXPECT_EQ(repairs->missing_vertices, holes);
  int outside = 0;
  double near_error = 0;  // Within a spacing of the data the fill still follows the field.
  for (size_t i = 0; i < mesh.vertex_count(); ++i) {
    const float v = mesh.fields[0].values[i];
    outside += !(v >= lo && v <= hi);
    if (mesh.positions[i].x() > 1.0f && mesh.positions[i].x() < 1.05f) {
      near_error = std::max(near_error, std::abs(double{v} - linear(mesh.positions[i])));
    }
  }
  std::printf("%zu vertices, %lld filled in %.2f s; within a spacing of the data off by at most %.3g\n",
              mesh.vertex_count(), static_cast<long long>(holes), seconds, near_error);
  EXPECT_EQ(outside, 0);
  EXPECT_LT(near_error, 0.2);
}

// A quadratic tetrahedral mesh made from a linear one by adding its edge midpoints (with the
// field's values there): the repair keeps every node, so the field is closer to the truth than
// on the corners alone; a quadratic hexahedral grid becomes the corners' grid exactly.
TEST(VolumeRepair, QuadraticCellsAreLinearisedKeepingTheirNodes) {
  const AnalyticField franke = Franke3d();
  VolumeMesh corners = JitteredTetMesh(franke.domain, 9, 0.3, 5);
  SampleField(corners, franke);
  VolumeMesh quadratic;
  quadratic.positions = corners.positions;
  std::map<std::pair<uint32_t, uint32_t>, uint32_t> midpoints;
  auto midpoint = [&](uint32_t a, uint32_t b) {
    const auto key = std::minmax(a, b);
    auto [it, added] =
        midpoints.try_emplace({key.first, key.second}, static_cast<uint32_t>(quadratic.positions.size()));
    if (added) quadratic.positions.push_back(0.5f * (corners.positions[a] + corners.positions[b]));
    return it->second;
  };
  for (size_t c = 0; c < corners.cell_count(); ++c) {
    const auto v = corners.cell(c);
    std::vector<uint32_t> nodes(v.begin(), v.end());
    for (auto [a, b] : {std::pair{0, 1}, {1, 2}, {2, 0}, {0, 3}, {1, 3}, {2, 3}}) nodes.push_back(midpoint(v[a], v[b]));
    quadratic.cell_types.push_back(24);
    if (quadratic.cell_offsets.empty()) quadratic.cell_offsets.push_back(0);
    quadratic.cell_vertices.insert(quadratic.cell_vertices.end(), nodes.begin(), nodes.end());
    quadratic.cell_offsets.push_back(static_cast<uint32_t>(quadratic.cell_vertices.size()));
  }
  SampleField(quadratic, franke);
  ASSERT_TRUE(CheckVolumeStructure(quadratic, {}).ok()) << CheckVolumeStructure(quadratic, {});
  auto repairs = RepairVolumeMesh(quadratic);
  ASSERT_TRUE(repairs.ok()) << repairs.status();
  EXPECT_EQ(repairs->linearised_cells, static_cast<int64_t>(corners.cell_count()));
  EXPECT_EQ(repairs->unused_vertices, 0);
  EXPECT_EQ(quadratic.cell_count(), 8 * corners.cell_count());
  EXPECT_EQ(repairs->degenerate_cells, 0);
  ASSERT_TRUE(ValidateVolumeMesh(quadratic, {}).ok()) << ValidateVolumeMesh(quadratic, {});
  EXPECT_NEAR(TotalVolume(quadratic), 1.0, 1e-5);
  const double coarse = RmsError(*Build(corners, "franke"), franke, 2000);
  const double fine = RmsError(*Build(quadratic, "franke"), franke, 2000);
  std::printf("Franke RMS: corners %.3g, quadratic nodes %.3g\n", coarse, fine);
  EXPECT_LT(fine, 0.7 * coarse);

  // One quadratic hexahedron (20 nodes: corners, then the 12 edge midpoints) and one quadratic
  // wedge: their corners' cells, the edge nodes unused.
  VolumeMesh hexes;
  hexes.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
  std::vector<uint32_t> nodes = {0, 1, 2, 3, 4, 5, 6, 7};
  for (int e = 0; e < 12; ++e) {
    nodes.push_back(static_cast<uint32_t>(hexes.positions.size()));
    hexes.positions.push_back(Vec3f(0.5f, 0.5f, 0.1f * static_cast<float>(e)));
  }
  hexes.cell_offsets = {0, 20};
  hexes.cell_types = {25};
  hexes.cell_vertices = nodes;
  ASSERT_TRUE(CheckVolumeStructure(hexes, {}).ok());
  auto hex_repairs = RepairVolumeMesh(hexes);
  ASSERT_TRUE(hex_repairs.ok()) << hex_repairs.status();
  EXPECT_EQ(hex_repairs->unused_vertices, 12);
  EXPECT_EQ(hexes.vertex_count(), 8u);
  EXPECT_EQ(hexes.cell_types[0], static_cast<uint8_t>(CellType::kHexahedron));
  EXPECT_NEAR(TotalVolume(hexes), 1.0, 1e-6);
}

TEST(VolumeRepair, EveryCellTypeIsTurnedBackFromTheMirroredOrder) {
  VolumeMesh mesh;
  mesh.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
  // Each cell's vertices in VTK's order mirrored through a plane: negative volume.
  const std::array<uint32_t, 8> hex = {4, 5, 6, 7, 0, 1, 2, 3};
  const std::array<uint32_t, 6> wedge = {4, 6, 5, 0, 2, 1};
  const std::array<uint32_t, 5> pyramid = {0, 3, 2, 1, 4};
  const std::array<uint32_t, 4> tet = {0, 2, 1, 4};
  mesh.AddCell(CellType::kHexahedron, hex);
  mesh.AddCell(CellType::kWedge, wedge);
  mesh.AddCell(CellType::kPyramid, pyramid);
  mesh.AddCell(CellType::kTetrahedron, tet);
  EXPECT_NE(ValidateVolumeMesh(mesh, {}).message().find("cell 0 (hexahedron) is inverted"), std::string_view::npos);
  auto repairs = RepairVolumeMesh(mesh);
  ASSERT_TRUE(repairs.ok()) << repairs.status();
  EXPECT_EQ(repairs->reoriented_cells, 4);
  EXPECT_TRUE(ValidateVolumeMesh(mesh, {}).ok()) << ValidateVolumeMesh(mesh, {});
  for (const auto& t : Tetrahedralize(mesh)) {
    EXPECT_GT(TetVolume(mesh.positions[t[0]], mesh.positions[t[1]], mesh.positions[t[2]], mesh.positions[t[3]]), 0);
  }
  // A hexahedron collapsed onto an edge (an O-grid's first ring) is kept; one whose corners all
  // lie at one point has no reading.
  VolumeMesh collapsed;
  collapsed.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 0, 1}, {1, 0, 1}, {1, 1, 1}};
  const std::array<uint32_t, 8> onto_axis = {0, 1, 2, 0, 3, 4, 5, 3};
  collapsed.AddCell(CellType::kHexahedron, onto_axis);
  auto kept = RepairVolumeMesh(collapsed);
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_TRUE(ValidateVolumeMesh(collapsed, {}).ok()) << ValidateVolumeMesh(collapsed, {});
  VolumeMesh point;
  point.positions = {{1, 1, 1}, {1, 1, 1}, {1, 1, 1}, {1, 1, 1}};
  const std::array<uint32_t, 4> nowhere = {0, 1, 2, 3};
  point.AddCell(CellType::kTetrahedron, nowhere);
  point.AddCell(CellType::kTetrahedron, nowhere);
  auto refused = RepairVolumeMesh(point);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("cell 0 (tetrahedron): all its corners lie at one point"),
            std::string_view::npos)
      << refused.status();
}

}  // namespace
}  // namespace lsqsurf::volume
