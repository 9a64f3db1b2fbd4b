#include "worker/volume/volume_mesh.h"

#include <gtest/gtest.h>

#include <cmath>

#include "worker/volume/cell_locator.h"
#include "worker/volume/synthetic.h"

namespace lsqsurf::volume {
namespace {

VolumeMesh UnitTet() {
  VolumeMesh m;
  m.positions = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
  const std::array<uint32_t, 4> t = {0, 1, 2, 3};
  m.AddCell(CellType::kTetrahedron, t);
  m.fields.push_back({"f", 1, {0, 1, 2, 3}});
  return m;
}

std::string Refusal(const VolumeMesh& m, const VolumeLimits& limits = {}) {
  const absl::Status s = ValidateVolumeMesh(m, limits);
  return s.ok() ? "" : std::string(s.message());
}

TEST(VolumeMesh, AcceptsAWellFormedTetrahedron) { EXPECT_EQ(Refusal(UnitTet()), ""); }

TEST(VolumeMesh, RefusesHostileCells) {
  VolumeMesh inverted = UnitTet();
  std::swap(inverted.cell_vertices[1], inverted.cell_vertices[2]);
  EXPECT_NE(Refusal(inverted).find("cell 0 (tetrahedron) is inverted"), std::string::npos) << Refusal(inverted);

  // A sliver and a cell collapsed onto a face are kept (RepairVolumeMesh counts them); a cell
  // whose corners all lie at one point is not.
  VolumeMesh flat = UnitTet();
  flat.positions[3] = {0.5f, 0.5f, 0};
  EXPECT_EQ(Refusal(flat), "");
  VolumeMesh point = UnitTet();
  for (Vec3f& p : point.positions) p = {0.25f, 0.25f, 0.25f};
  EXPECT_NE(Refusal(point).find("all its corners lie at one point"), std::string::npos) << Refusal(point);

  VolumeMesh out_of_range = UnitTet();
  out_of_range.cell_vertices[3] = 7;
  EXPECT_NE(Refusal(out_of_range).find("refers to vertex 7"), std::string::npos) << Refusal(out_of_range);

  VolumeMesh repeated = UnitTet();
  repeated.cell_vertices[3] = 0;
  EXPECT_EQ(Refusal(repeated), "");

  VolumeMesh triangle = UnitTet();
  triangle.cell_types[0] = 5;
  EXPECT_NE(Refusal(triangle).find("is a triangle"), std::string::npos) << Refusal(triangle);

  VolumeMesh nan_value = UnitTet();
  nan_value.fields[0].values[2] = std::nanf("");
  EXPECT_NE(Refusal(nan_value).find("'f' is NaN or infinite at vertex 2"), std::string::npos) << Refusal(nan_value);

  VolumeMesh nan_position = UnitTet();
  nan_position.positions[1].x() = std::nanf("");
  EXPECT_NE(Refusal(nan_position).find("vertex 1"), std::string::npos);

  VolumeMesh short_field = UnitTet();
  short_field.fields[0].values.pop_back();
  EXPECT_NE(Refusal(short_field).find("3 values for 4 vertices"), std::string::npos) << Refusal(short_field);
}

TEST(VolumeMesh, RefusesCountsOverTheLimitsAsResourceExhausted) {
  VolumeLimits limits;
  limits.max_vertices = 3;
  EXPECT_EQ(ValidateVolumeMesh(UnitTet(), limits).code(), absl::StatusCode::kResourceExhausted);
  limits = {};
  limits.max_cells = 0;
  EXPECT_EQ(ValidateVolumeMesh(UnitTet(), limits).code(), absl::StatusCode::kResourceExhausted);
}

TEST(VolumeMesh, EveryCellTypeCutsIntoPositiveTetrahedraOfTheSameVolume) {
  // A unit cube as one hexahedron and as the two wedges that split it along a diagonal plane;
  // a square pyramid of height 1.
  VolumeMesh hex;
  hex.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
  const std::array<uint32_t, 8> h = {0, 1, 2, 3, 4, 5, 6, 7};
  hex.AddCell(CellType::kHexahedron, h);
  VolumeMesh wedges;
  wedges.positions = hex.positions;
  // VTK's wedge order: the base (0, 1, 2) turns clockwise seen from the top face.
  const std::array<uint32_t, 6> w1 = {0, 2, 1, 4, 6, 5}, w2 = {0, 3, 2, 4, 7, 6};
  wedges.AddCell(CellType::kWedge, w1);
  wedges.AddCell(CellType::kWedge, w2);
  VolumeMesh pyramid;
  pyramid.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, {0.5f, 0.5f, 1}};
  const std::array<uint32_t, 5> p = {0, 1, 2, 3, 4};
  pyramid.AddCell(CellType::kPyramid, p);
  for (const auto& [mesh, volume] : {std::pair{&hex, 1.0}, std::pair{&wedges, 1.0}, std::pair{&pyramid, 1.0 / 3}}) {
    ASSERT_TRUE(ValidateVolumeMesh(*mesh, {}).ok()) << ValidateVolumeMesh(*mesh, {});
    double total = 0;
    for (const auto& t : Tetrahedralize(*mesh)) {
      const double v =
          TetVolume(mesh->positions[t[0]], mesh->positions[t[1]], mesh->positions[t[2]], mesh->positions[t[3]]);
      EXPECT_GT(v, 0);
      total += v;
    }
    EXPECT_NEAR(total, volume, 1e-6);
  }
}

TEST(CellLocator, InterpolatesLinearFieldsExactlyAndKnowsTheDomain) {
  VolumeMesh mesh = JitteredTetMesh(core::Box3(Vec3d(0, 0, 0), Vec3d(2, 1, 1)), 7, 0.3, 4);
  VertexField f{"lin", 1, {}};
  for (const Vec3f& p : mesh.positions) f.values.push_back(1 + 2 * p.x() - p.y() + 0.5f * p.z());
  mesh.fields.push_back(f);
  CellLocator locator(mesh);
  for (const Vec3d& x : {Vec3d(0.3, 0.2, 0.9), Vec3d(1.7, 0.5, 0.5), Vec3d(1e-7, 0.5, 0.5), Vec3d(2, 1, 1)}) {
    const auto at = locator.Locate(x);
    ASSERT_GE(at.tet, 0) << x.transpose();
    EXPECT_NEAR(locator.Interpolate(mesh.fields[0].values, 1, 0, at), 1 + 2 * x.x() - x.y() + 0.5 * x.z(), 1e-5);
  }
  EXPECT_FALSE(locator.Contains(Vec3d(2.01, 0.5, 0.5)));
  EXPECT_FALSE(locator.Contains(Vec3d(-0.5, 0.5, 0.5)));
}

}  // namespace
}  // namespace lsqsurf::volume
