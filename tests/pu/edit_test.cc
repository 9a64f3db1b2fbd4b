// Local edits of PU functions: only the fits in a ball change, and F outside their supports
// stays the same to the last bit.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>

#include "absl/container/flat_hash_set.h"
#include "tests/polyhedra.h"
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

// Two evaluations of F alike to the last bit (NaN counts as equal to NaN).
bool SameEvaluation(const core::FieldGradient& a, const core::FieldGradient& b) {
  return (a.value == b.value || (std::isnan(a.value) && std::isnan(b.value))) && a.gradient == b.gradient &&
         a.defined == b.defined;
}

// Random points near the torus: counts those that changed, and fails on any change beyond `reach`.
int CountChanged(const PuFunction& a, const PuFunction& b, const Vec3d& centre, double reach) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(-1.4, 1.4);
  int changed = 0, outside = 0;
  for (int i = 0; i < 20'000; ++i) {
    const Vec3d x(u(rng), u(rng), u(rng) * 0.35);
    const core::FieldGradient fa = a.ValueAndGradient(x), fb = b.ValueAndGradient(x);
    const bool same = SameEvaluation(fa, fb);
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

// An edit updates the support index only where it changed; the function read back from its
// bytes has the index built anew. The two must evaluate alike everywhere, to the last bit.
void ExpectSameAsRebuiltIndex(const PuFunction& edited) {
  auto rebuilt = DeserializePu(SerializePu(edited));
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1.4, 1.4);
  int differ = 0;
  for (int i = 0; i < 20'000; ++i) {
    const Vec3d x(u(rng), u(rng), u(rng) * 0.35);
    differ += !SameEvaluation(edited.ValueAndGradient(x), (*rebuilt)->ValueAndGradient(x));
  }
  EXPECT_EQ(differ, 0);
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
  ExpectSameAsRebuiltIndex(**edited);
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
  ExpectSameAsRebuiltIndex(**edited);
  // A second edit overlapping the first, of the edited function (its split cells included).
  edit.action = PuEditAction::kSetDegree;
  edit.degree = 2;
  edit.centre = Vec3d(0.05, 0.75, 0);
  auto again = EditPu(**edited, edit, f.ctx);
  ASSERT_TRUE(again.ok()) << again.status();
  ExpectSameAsRebuiltIndex(**again);
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
  ExpectSameAsRebuiltIndex(**edited);
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

// The surface of the base function, traced and kept (as the service keeps it beside the function).
KeptSurface KeepSurface(const PuFunction& f) {
  core::LocalJobContext ctx;
  PuExtractParams params;
  params.marching.trace = true;
  auto r = Extract(f, params, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  KeptSurface kept;
  if (!r.ok()) return kept;
  kept.mesh = std::move(r->mesh);
  kept.trace = std::move(r->trace);
  kept.params = params;
  // Through the stored form, as an edit job reads it.
  auto read = DeserializeSurface(SerializeSurface(kept.mesh, kept.trace, kept.params));
  EXPECT_TRUE(read.ok()) << read.status();
  return read.ok() ? *std::move(read) : kept;
}

// Re-extracting only near the edit: the kept mesh's vertices beyond the changed ball stay to the
// last bit, the join is as closed as a whole extraction of the edited function, the new part lies
// on the edited surface, and the volume agrees with the whole extraction's.
void ExpectLocalMatchesWhole(const PuFunction& base, const PuEdit& edit, bool closed) {
  core::LocalJobContext ctx;
  const KeptSurface kept = KeepSurface(base);
  PuEditStats stats;
  auto edited = EditPu(base, edit, ctx, &stats);
  ASSERT_TRUE(edited.ok()) << edited.status();
  auto local = ExtractEdited(base, **edited, stats, kept, PuExtractParams{}, ctx);
  ASSERT_TRUE(local.ok()) << local.status();
  auto whole = Extract(**edited, PuExtractParams{}, ctx);
  ASSERT_TRUE(whole.ok()) << whole.status();
  const core::MeshTopology t = core::AnalyzeTopology(core::WeldByPosition(local->mesh));
  const core::MeshTopology w = core::AnalyzeTopology(core::WeldByPosition(whole->mesh));
  EXPECT_EQ(t.non_manifold_edges, 0);
  EXPECT_EQ(t.components, w.components);
  if (closed) {
    EXPECT_TRUE(t.watertight());
    EXPECT_EQ(t.euler_characteristic(), w.euler_characteristic());
    EXPECT_NEAR(core::EnclosedVolume(local->mesh), core::EnclosedVolume(whole->mesh),
                2e-4 * std::abs(core::EnclosedVolume(whole->mesh)));
  } else {
    EXPECT_GT(t.boundary_edges, 0);
    EXPECT_NEAR(static_cast<double>(t.boundary_edges), static_cast<double>(w.boundary_edges),
                0.2 * static_cast<double>(w.boundary_edges));
  }
  EXPECT_EQ(local->trace.vertex_edges.size(), local->mesh.vertices.size());
  EXPECT_EQ(local->trace.face_cells.size(), local->mesh.faces.size());
  // Kept vertices far from the edit are all still there, unmoved.
  absl::flat_hash_set<std::array<float, 3>> positions;
  for (const core::Vec3f& v : local->mesh.vertices) positions.insert({v.x(), v.y(), v.z()});
  int far = 0, kept_far = 0;
  for (const core::Vec3f& v : kept.mesh.vertices) {
    if ((v.cast<double>() - edit.centre).norm() < stats.reach + 0.15) continue;
    ++far;
    kept_far += positions.contains({v.x(), v.y(), v.z()});
  }
  EXPECT_GT(far, 1000);
  EXPECT_EQ(kept_far, far);
  // Near the edit the vertices lie on the edited surface (within a thousandth of the torus' size).
  int near = 0;
  for (const core::Vec3f& v : local->mesh.vertices) {
    if ((v.cast<double>() - edit.centre).norm() > stats.reach) continue;
    ++near;
    const core::FieldGradient g = (*edited)->ValueAndGradient(v.cast<double>());
    EXPECT_LT(std::abs(g.value) / std::max(g.gradient.norm(), 1e-12), 1e-3) << v.transpose();
  }
  EXPECT_GT(near, 50);
  EXPECT_LT(local->mesh.faces.size(), whole->mesh.faces.size() * 11 / 10);
  EXPECT_GT(local->stats.seam_edges, 20);
  EXPECT_GT(local->stats.replaced_faces, 100);
  std::printf("replaced %lld faces by %lld along %lld seam edges (whole: %zu faces, local: %zu)\n",
              static_cast<long long>(local->stats.replaced_faces), static_cast<long long>(local->stats.crossings),
              static_cast<long long>(local->stats.seam_edges), whole->mesh.faces.size(), local->mesh.faces.size());
}

TEST(PuEdit, LocalReExtractionJoinsTheKeptMesh) {
  Fixture f;
  ASSERT_NE(f.base, nullptr);
  PuEdit edit;
  edit.centre = Vec3d(1.3, 0, 0);
  edit.radius = 0.15;
  edit.degree = 1;
  ExpectLocalMatchesWhole(*f.base, edit, true);
  edit.action = PuEditAction::kRefit;
  edit.centre = Vec3d(0, 0.7, 0);
  edit.radius = 0.1;
  edit.error_threshold = 1e-5;
  ExpectLocalMatchesWhole(*f.base, edit, true);
  edit.action = PuEditAction::kRemove;
  edit.centre = Vec3d(0, -1.3, 0);
  edit.radius = 0.12;
  ExpectLocalMatchesWhole(*f.base, edit, false);
}

// Refitting in a ball on a pentagonal pyramid's 50° base edge: the local join came out open and
// in two pieces. It is refused (the edit job then extracts the whole surface), or it is closed.
TEST(PuEdit, ALocalJoinNeverOpensAClosedSurface) {
  const double elevation = 40 * std::numbers::pi / 180;
  const double offset = 0.3;
  const testing::TurnedPolyhedron pyramid(testing::PentagonalPyramidNormals(), offset);
  // The middle of the base edge under sides 0 and 1: on the base plane, on the bisector of their
  // azimuths, where a side at that azimuth meets the base.
  const double reach = (offset + offset * std::sin(elevation)) / std::cos(elevation);
  const double azimuth = std::numbers::pi / 5;
  const Vec3d edge_middle = pyramid.World(Vec3d(reach * std::cos(azimuth), reach * std::sin(azimuth), -offset));
  core::LocalJobContext ctx;
  auto base = BuildPu(pyramid.Sample(150'000), PuParams{}, ctx);
  ASSERT_TRUE(base.ok()) << base.status();
  ASSERT_LT(std::abs((*base)->Value(edge_middle).value), 1e-3);
  const KeptSurface kept = KeepSurface(**base);
  ASSERT_TRUE(core::AnalyzeTopology(core::WeldByPosition(kept.mesh)).watertight());
  PuEdit edit;
  edit.centre = edge_middle;
  edit.radius = 0.03;
  edit.action = PuEditAction::kRefit;
  edit.error_threshold = 1e-5;
  PuEditStats stats;
  auto edited = EditPu(**base, edit, ctx, &stats);
  ASSERT_TRUE(edited.ok()) << edited.status();
  auto local = ExtractEdited(**base, **edited, stats, kept, PuExtractParams{}, ctx);
  if (!local.ok()) {
    EXPECT_EQ(local.status().code(), absl::StatusCode::kFailedPrecondition) << local.status();
    return;
  }
  const core::MeshTopology t = core::AnalyzeTopology(core::WeldByPosition(local->mesh));
  EXPECT_TRUE(t.watertight());
  EXPECT_EQ(t.components, 1);
}

TEST(PuEdit, LocalReExtractionRefusesOtherParameters) {
  Fixture f;
  ASSERT_NE(f.base, nullptr);
  const KeptSurface kept = KeepSurface(*f.base);
  PuEdit edit;
  edit.centre = Vec3d(1.3, 0, 0);
  edit.radius = 0.15;
  PuEditStats stats;
  auto edited = EditPu(*f.base, edit, f.ctx, &stats);
  ASSERT_TRUE(edited.ok()) << edited.status();
  PuExtractParams other;
  other.cell_size = 3;
  EXPECT_EQ(ExtractEdited(*f.base, **edited, stats, kept, other, f.ctx).status().code(),
            absl::StatusCode::kFailedPrecondition);
  // A trace that does not fit its mesh is refused too, not trusted.
  KeptSurface broken = kept;
  broken.trace.face_cells.pop_back();
  EXPECT_EQ(ExtractEdited(*f.base, **edited, stats, broken, PuExtractParams{}, f.ctx).status().code(),
            absl::StatusCode::kFailedPrecondition);
  std::string bytes = SerializeSurface(kept.mesh, kept.trace, kept.params);
  bytes.resize(bytes.size() / 2);
  EXPECT_EQ(DeserializeSurface(bytes).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace lsqsurf::pu
