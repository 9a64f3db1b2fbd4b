#include "worker/io/obj_xyz.h"

#include <gtest/gtest.h>

namespace lsqsurf::io {
namespace {

TEST(Obj, RoundTripKeepsGeometryAndNormals) {
  core::TriangleMesh m;
  m.vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0.5f}, {0.1f, 0.2f, 0.3f}};
  m.normals = {{0, 0, 1}, {0, 0, 1}, {0, 1, 0}, {1, 0, 0}};
  m.faces = {{0, 1, 2}, {0, 2, 3}};
  auto back = ParseObj(EncodeObj(m), "t.obj");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->vertices, m.vertices);
  EXPECT_EQ(back->normals, m.normals);
  EXPECT_EQ(back->faces, m.faces);
}

TEST(Obj, FaceFormsAndNegativeIndices) {
  auto m = ParseObj("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1/1 3//1 -1\n", "t.obj");
  ASSERT_TRUE(m.ok()) << m.status();
  ASSERT_EQ(m->faces.size(), 2u);
  EXPECT_EQ(m->faces[1], (core::Triangle{0, 2, 3}));
}

TEST(Obj, ErrorsCarryLineNumbers) {
  auto bad = ParseObj("v 0 0 0\nv 1 0\n", "t.obj");
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(std::string(bad.status().message()).find("line 2"), std::string::npos);
  auto range = ParseObj("v 0 0 0\nf 1 2 3\n", "t.obj");
  ASSERT_FALSE(range.ok());
  EXPECT_NE(std::string(range.status().message()).find("outside"), std::string::npos);
}

TEST(Xyz, RoundTripWithAndWithoutNormals) {
  core::PointCloud c;
  c.positions = {{1.5f, -2, 3e-7f}, {0, 0, 1}};
  auto plain = ParseXyz(EncodeXyz(c), "p.xyz");
  ASSERT_TRUE(plain.ok());
  EXPECT_EQ(plain->positions, c.positions);
  EXPECT_FALSE(plain->has_normals());
  c.normals = {{0, 0, 1}, {1, 0, 0}};
  auto oriented = ParseXyz(EncodeXyz(c), "p.xyzn");
  ASSERT_TRUE(oriented.ok());
  EXPECT_EQ(oriented->normals, c.normals);
}

TEST(Xyz, RejectsMixedColumnsAndGarbage) {
  EXPECT_FALSE(ParseXyz("1 2 3\n1 2 3 0 0 1\n", "m.xyz").ok());
  auto garbage = ParseXyz("# header\n1 2 x\n", "g.xyz");
  ASSERT_FALSE(garbage.ok());
  EXPECT_NE(std::string(garbage.status().message()).find("line 2"), std::string::npos);
  EXPECT_FALSE(ParseXyz("\n# nothing\n", "e.xyz").ok());
}

}  // namespace
}  // namespace lsqsurf::io
