// Lattice edges pierced by a part thinner than the edge: a slab between two corners just outside
// its faces, with a ring of corners inside it around the edge between them. Marching alone cuts
// the slab along that edge with a tube (a tunnel through the slab); with the ends counted inside
// the slab is whole there.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "worker/core/mesh_metrics.h"
#include "worker/extract/marching_tets.h"

namespace lsqsurf::extract::internal {
namespace {

using core::Vec3d;

// |z| − half_thickness: the exact distance to the slab's faces outside it.
class SlabField final : public core::ImplicitFunction {
 public:
  explicit SlabField(double half_thickness) : half_(half_thickness) {}
  core::FieldValue Value(const Vec3d& x) const override { return {std::abs(x.z()) - half_, true}; }
  core::FieldGradient ValueAndGradient(const Vec3d& x) const override {
    return {std::abs(x.z()) - half_, Vec3d(0, 0, x.z() < 0 ? -1 : 1), true};
  }

 private:
  double half_;
};

constexpr double kHalfThickness = 0.1;
constexpr CornerKey kTop = 0, kBottom = 1;  // The ends of the pierced edge; the ring follows.
constexpr int kRing = 6;

// Six tetrahedra around the edge top–bottom (along z), the ring in the slab's middle plane.
struct Star {
  explicit Star(double end_height) {
    positions = {Vec3d(0, 0, end_height), Vec3d(0, 0, -end_height)};
    for (int k = 0; k < kRing; ++k) {
      const double a = 2 * std::numbers::pi * k / kRing;
      positions.push_back(0.3 * Vec3d(std::cos(a), std::sin(a), 0));
    }
    for (CornerKey k = 0; k < kRing; ++k) tets.push_back({kTop, kBottom, 2 + k, 2 + (k + 1) % kRing});
    for (CornerKey k = 0; k < positions.size(); ++k) values[k] = field.Value(positions[k]);
  }
  void ForEachTet(const TetVisitor& visit) const {
    for (const TetCorners& t : tets) visit(t, 0);
  }
  Vec3d Position(CornerKey k) const { return positions[k]; }

  SlabField field{kHalfThickness};
  std::vector<Vec3d> positions;
  std::vector<TetCorners> tets;
  absl::flat_hash_map<CornerKey, core::FieldValue> values;
};

absl::StatusOr<absl::flat_hash_map<CornerKey, Vec3d>> Pierced(const Star& star) {
  core::LocalJobContext ctx;
  return PiercedCorners(
      star.field, [&](const TetVisitor& visit) { star.ForEachTet(visit); }, star.values,
      [&](CornerKey k) { return star.Position(k); }, ctx);
}

// Faces with vertices on both sides of the slab's middle plane: what joins its two faces.
int FacesAcrossTheSlab(const core::TriangleMesh& mesh) {
  int across = 0;
  for (const core::Triangle& t : mesh.faces) {
    bool above = false, below = false;
    for (uint32_t v : t) (mesh.vertices[v].z() > 0 ? above : below) = true;
    across += above && below ? 1 : 0;
  }
  return across;
}

TEST(PiercedCorners, CornersJustOutsideBothFacesAreCountedInsideOnTheFaces) {
  // The ends 2 % of the edge outside the faces (under kPiercedShare).
  const double end_height = kHalfThickness / (1 - 2 * 0.02);
  Star star(end_height);
  auto pierced = Pierced(star);
  ASSERT_TRUE(pierced.ok()) << pierced.status();
  ASSERT_EQ(pierced->size(), 2u);
  ASSERT_TRUE(pierced->contains(kTop) && pierced->contains(kBottom));
  // Moved straight onto the faces they lay beside.
  EXPECT_NEAR((pierced->at(kTop) - Vec3d(0, 0, kHalfThickness)).norm(), 0, 1e-12);
  EXPECT_NEAR((pierced->at(kBottom) - Vec3d(0, 0, -kHalfThickness)).norm(), 0, 1e-12);

  core::LocalJobContext ctx;
  const auto for_each_tet = [&](const TetVisitor& visit) { star.ForEachTet(visit); };
  const auto position = [&](CornerKey k) { return star.Position(k); };
  MarchingOptions options;
  options.max_patch_triangles = 0;
  auto tunnel = MarchTetrahedra(star.field, for_each_tet, star.values, position, options, {}, ctx);
  ASSERT_TRUE(tunnel.ok()) << tunnel.status();
  // A tube around the edge from face to face: an annulus (two border loops, Euler
  // characteristic 0).
  const core::MeshTopology tube = core::AnalyzeTopology(tunnel->mesh);
  EXPECT_EQ(tube.boundary_loops, 2);
  EXPECT_EQ(tube.euler_characteristic(), 0);
  EXPECT_EQ(FacesAcrossTheSlab(tunnel->mesh), static_cast<int>(tunnel->mesh.faces.size()));

  // Counted inside, every corner of the star is: no surface cuts the slab there.
  for (const auto& [key, on_surface] : *pierced) star.values[key].value = -std::numeric_limits<double>::denorm_min();
  auto whole = MarchTetrahedra(star.field, for_each_tet, star.values, position, options, {}, ctx, &*pierced);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_TRUE(whole->mesh.faces.empty());
}

TEST(PiercedCorners, EdgesThatTheSurfaceDoesNotPierceAreLeft) {
  // Ends farther out than kPiercedShare of the edge: not just outside.
  EXPECT_TRUE(Pierced(Star(kHalfThickness / (1 - 2 * 0.1)))->empty());
  // Both ends just outside the same face: the midpoint is outside too.
  Star same_side(kHalfThickness / (1 - 2 * 0.02));
  same_side.positions[kBottom] = Vec3d(0.05, 0, same_side.positions[kTop].z());
  for (CornerKey k = 0; k < same_side.positions.size(); ++k) {
    same_side.values[k] = same_side.field.Value(same_side.positions[k]);
  }
  EXPECT_TRUE(Pierced(same_side)->empty());
}

}  // namespace
}  // namespace lsqsurf::extract::internal
