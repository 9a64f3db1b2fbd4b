// Local edits of PU functions: only the fits in a ball change, and F outside their supports
// stays the same to the last bit.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/pu/pu.h"

namespace lsqsurf::pu {
namespace {

using core::Vec3d;

struct Fixture {
  core::LocalJobContext ctx;
  std::unique_ptr<PuFunction> base;
  Fixture() {
    auto built = BuildPu(testing::TorusCloud(30'000, 1.0, 0.3), PuParams{}, ctx);
    EXPECT_TRUE(built.ok()) << built.status();
    if (built.ok()) base = *std::move(built);
  }
};

// Random points near the torus: counts those that changed, and fails on any change beyond `reach`.
int CountChanged(const PuFunction& a, const PuFunction& b, const Vec3d& centre, double reach) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(-1.4, 1.4);
  int changed = 0, outside = 0;
  for (int i = 0; i < 20'000; ++i) {
    const Vec3d x(u(rng), u(rng), u(rng) * 0.35);
    const core::FieldGradient fa = a.ValueAndGradient(x), fb = b.ValueAndGradient(x);
    const bool same = (fa.value == fb.value || (std::isnan(fa.value) && std::isnan(fb.value))) &&
                      fa.gradient == fb.gradient && fa.defined == fb.defined;
    if ((x - centre).norm() >= reach) {
      ++outside;
      EXPECT_TRUE(same) << "at " << x.transpose() << ": " << fa.value << " vs " << fb.value;
    } else {
      changed += !same;
    }
  }
  EXPECT_GT(outside, 10'000);
  return changed;
}

core::MeshTopology Topology(const PuFunction& f, core::TriangleMesh* mesh = nullptr) {
  core::LocalJobContext ctx;
  auto r = Extract(f, PuExtractParams{}, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return {};
  if (mesh) *mesh = r->mesh;
  return core::AnalyzeTopology(core::WeldByPosition(r->mesh));
}

TEST(PuEdit, LoweringTheDegreeInABallChangesNothingOutsideIt) {
  Fixture f;
  ASSERT_NE(f.base, nullptr);
  PuEdit edit;
  edit.centre = Vec3d(1.3, 0, 0);  // On the torus' outer equator.
  edit.radius = 0.15;
  edit.degree = 1;
  PuEditStats stats;
  auto edited = EditPu(*f.base, edit, f.ctx, &stats);
  ASSERT_TRUE(edited.ok()) << edited.status();
  EXPECT_GT(stats.fits_replaced, 0);
  // Refitted in place: as many fits as before.
  const PuStats& s = f.base->stats();
  int64_t fits = s.quadric_fits + s.sharp_edges + s.sharp_corners;
  for (int64_t n : s.fits_per_degree) fits += n;
  EXPECT_EQ(stats.fits_after, fits);
  EXPECT_GT(CountChanged(*f.base, **edited, edit.centre, stats.reach), 100);
  // Inside the ball every fit is now planar, and the surface is still one closed torus.
  core::TriangleMesh mesh;
  const core::MeshTopology t = Topology(**edited, &mesh);
  EXPECT_TRUE(t.watertight());
  EXPECT_EQ(t.euler_characteristic(), 0);
  for (const auto& a : mesh.vertex_attributes) {
    if (a.name != "degree") continue;
    for (size_t i = 0; i < mesh.vertices.size(); ++i) {
      if ((mesh.vertices[i].cast<double>() - edit.centre).norm() < edit.radius * 0.5) {
        EXPECT_LE(a.values[i], 1.0f);
      }
    }
  }
}

TEST(PuEdit, RefittingSplitsCellsOnlyInTheBall) {
  Fixture f;
  ASSERT_NE(f.base, nullptr);
  PuEdit edit;
  edit.centre = Vec3d(0, 0.7, 0);  // On the inner equator.
  edit.radius = 0.1;
  edit.action = PuEditAction::kRefit;
  edit.error_threshold = 1e-5;
  PuEditStats stats;
  auto edited = EditPu(*f.base, edit, f.ctx, &stats);
  ASSERT_TRUE(edited.ok()) << edited.status();
  // Smaller cells in the ball: more fits than it replaced, and F differs there only.
  const PuStats& s = f.base->stats();
  int64_t fits = s.quadric_fits + s.sharp_edges + s.sharp_corners;
  for (int64_t n : s.fits_per_degree) fits += n;
  EXPECT_GT(stats.fits_after, fits);
  EXPECT_GT(CountChanged(*f.base, **edited, edit.centre, stats.reach), 0);
  EXPECT_TRUE(Topology(**edited).watertight());
}

TEST(PuEdit, RemovingOpensAHoleWhereTheBallWas) {
  Fixture f;
  ASSERT_NE(f.base, nullptr);
  PuEdit edit;
  edit.centre = Vec3d(0, -1.3, 0);
  edit.radius = 0.12;
  edit.action = PuEditAction::kRemove;
  PuEditStats stats;
  auto edited = EditPu(*f.base, edit, f.ctx, &stats);
  ASSERT_TRUE(edited.ok()) << edited.status();
  EXPECT_GT(stats.points_removed, 100);
  core::TriangleMesh mesh;
  const core::MeshTopology t = Topology(**edited, &mesh);
  EXPECT_GT(t.boundary_edges, 0);  // The hole.
  EXPECT_EQ(t.non_manifold_edges, 0);
  for (const auto& v : mesh.vertices) EXPECT_GT((v.cast<double>() - edit.centre).norm(), 0.5 * edit.radius);

  edit.centre = Vec3d(5, 5, 5);
  EXPECT_EQ(EditPu(*f.base, edit, f.ctx).status().code(), absl::StatusCode::kFailedPrecondition);
  edit.radius = -1;
  EXPECT_EQ(EditPu(*f.base, edit, f.ctx).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::pu
