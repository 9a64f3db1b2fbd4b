// CSG of analytic primitives and of PU functions, against the exact solids.
#include "worker/csg/csg.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <numbers>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/strings.h"
#include "worker/csg/expression.h"
#include "worker/jobs/csg_job.h"
#include "worker/pu/pu.h"

namespace lsqsurf::csg {
namespace {

using core::Vec3d;

absl::StatusOr<Operand> NoJobs(const std::string& id) { return absl::NotFoundError(core::StrCat("no job ", id)); }

struct Solid {
  std::unique_ptr<CsgFunction> function;
  core::TriangleMesh mesh;
  core::MeshTopology topology;
  double volume = 0;
};

Solid Extract(const std::string& text, double cell_size, const OperandResolver& resolve = NoJobs) {
  Solid s;
  auto root = ParseCsg(text);
  EXPECT_TRUE(root.ok()) << root.status();
  if (!root.ok()) return s;
  auto f = BuildCsg(*root, resolve);
  EXPECT_TRUE(f.ok()) << f.status();
  if (!f.ok()) return s;
  s.function = *std::move(f);
  CsgParams params;
  params.cell_size = cell_size;
  core::LocalJobContext ctx;
  auto r = ExtractCsg(*s.function, params, ctx);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return s;
  s.mesh = std::move(r->mesh);
  s.topology = core::AnalyzeTopology(core::WeldByPosition(s.mesh));
  s.volume = core::EnclosedVolume(s.mesh);
  return s;
}

void ExpectClosed(const Solid& s, int genus = 0) {
  SCOPED_TRACE(core::StrCat(s.mesh.faces.size(), " faces, ", s.topology.boundary_edges, " boundary, ",
                            s.topology.non_manifold_edges, " non-manifold, ", s.topology.misoriented_edges,
                            " misoriented edges, ", s.topology.components, " components"));
  EXPECT_TRUE(s.topology.watertight());
  EXPECT_TRUE(s.topology.consistently_oriented());
  EXPECT_EQ(s.topology.components, 1);
  EXPECT_EQ(s.topology.euler_characteristic(), 2 - 2 * genus);
}

TEST(CsgExpression, ParsesOperationsPrimitivesTransformsAndJobs) {
  auto root = ParseCsg(
      "difference(job:ab-12, sphere(c=0.1,0.2,0.3 r=0.05), rotate(axis=1, 0, 0 deg=90 "
      "translate(t=0,0,1 box(size=2))), union(job:x7 torus(R=1 r=0.25) job:ab-12))");
  ASSERT_TRUE(root.ok()) << root.status();
  EXPECT_EQ(root->kind, NodeKind::kDifference);
  ASSERT_EQ(root->children.size(), 4u);
  EXPECT_EQ(root->children[1].Vector("c"), Vec3d(0.1, 0.2, 0.3));
  const CsgNode& box = root->children[2].children[0].children[0];
  EXPECT_EQ(box.kind, NodeKind::kBox);
  EXPECT_EQ(box.Vector("min"), Vec3d(-1, -1, -1));
  EXPECT_EQ(root->children[3].children[1].Vector("axis"), Vec3d(0, 0, 1));  // The default.
  EXPECT_EQ(ReferencedJobs(*root), (std::vector<std::string>{"ab-12", "x7"}));
}

TEST(CsgExpression, ErrorsNameTheColumnAndTheFix) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"sphre(r=1)", "column 1: unknown name 'sphre'"},
      {"sphere(r=1", "missing ')'"},
      {"sphere(c=1,2 r=1)", "three numbers"},
      {"sphere(c=0,0,0)", "needs r="},
      {"sphere(r=-1)", "must be positive"},
      {"union(sphere(r=1))", "at least 2 operands"},
      {"box(min=0,0,0 max=1,-1,1)", "min must be below max"},
      {"box(min=0,0,0 max=1,1,1 size=2)", "either min= and max= or size="},
      {"translate(t=1,0,0 sphere(r=1) sphere(r=2))", "exactly one operand"},
      {"cylinder(a=0,0,0 b=0,0,0 r=1)", "a and b apart"},
      {"sphere(r=1) sphere(r=2)", "unexpected text"},
      {"sphere(q=1 r=1)", "no argument 'q'"},
      {"job:", "expected a job id"},
      {"sphere(r=nan)", "finite number"},
  };
  for (const auto& [text, message] : cases) {
    auto root = ParseCsg(text);
    ASSERT_FALSE(root.ok()) << text;
    EXPECT_EQ(root.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(root.status().message().find(message), std::string::npos) << text << ": " << root.status().message();
  }
  std::string deep;
  for (int i = 0; i < 70; ++i) deep += "translate(t=0,0,0 ";
  EXPECT_FALSE(ParseCsg(deep + "sphere(r=1)" + std::string(70, ')')).ok());
}

TEST(CsgFunction, UnboundedAndDisjointSolidsAreRefused) {
  auto plane = ParseCsg("plane(n=0,0,1)");
  ASSERT_TRUE(plane.ok());
  EXPECT_EQ(BuildCsg(*plane, NoJobs).status().code(), absl::StatusCode::kInvalidArgument);
  auto disjoint = ParseCsg("intersection(sphere(c=0,0,0 r=1) sphere(c=5,0,0 r=1))");
  ASSERT_TRUE(disjoint.ok());
  EXPECT_EQ(BuildCsg(*disjoint, NoJobs).status().code(), absl::StatusCode::kInvalidArgument);
  auto missing = ParseCsg("union(job:nope sphere(r=1))");
  ASSERT_TRUE(missing.ok());
  const absl::Status s = BuildCsg(*missing, NoJobs).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kNotFound);
  EXPECT_NE(s.message().find("job:nope"), std::string::npos);
}

// Solids whose extraction would grow without bound are refused before any work is done: one too
// large for its cells to mean anything in doubles, or one whose surface needs more cells than a
// job may use. The estimate that decides it follows the real seed count; a cancelled extraction
// stops while it seeds.
TEST(CsgExtraction, SolidsTooLargeToExtractAreRefusedBeforeTheyGrow) {
  for (const char* huge :
       {"sphere(r=1e308)", "box(min=-1e300,0,0 max=1e300,1,1)", "scale(s=1e9 scale(s=1e9 sphere(r=10)))"}) {
    auto root = ParseCsg(huge);
    ASSERT_TRUE(root.ok()) << huge;
    const absl::Status s = BuildCsg(*root, NoJobs).status();
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << huge;
    EXPECT_NE(s.message().find("model units across"), std::string::npos) << s;
  }
  auto sphere = ParseCsg("sphere(r=1)");
  ASSERT_TRUE(sphere.ok());
  auto f = BuildCsg(*sphere, NoJobs);
  ASSERT_TRUE(f.ok());
  CsgParams fine;
  fine.cell_size = 1.2e-4;  // About 1.5e9 cells along the surface.
  core::LocalJobContext ctx;
  const auto refused = ExtractCsg(**f, fine, ctx);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted) << refused.status();
  EXPECT_NE(refused.status().message().find("larger cell_size"), std::string::npos) << refused.status();

  CsgParams coarse;
  coarse.cell_size = 0.02;
  const double estimate = *EstimateSurfaceCells(**f, coarse);
  CsgStats stats;
  ASSERT_TRUE(ExtractCsg(**f, coarse, ctx, &stats).ok());
  // A sphere crosses 1.5·area/h² cells on average over its normals; the estimate takes √3.
  EXPECT_GT(static_cast<double>(stats.seeds), 0.6 * estimate) << estimate;
  EXPECT_LT(static_cast<double>(stats.seeds), 1.2 * estimate) << estimate;

  CsgParams allowed;
  allowed.cell_size = 1.5e-3;  // About 1.2e7 cells: within the limit, and long to seed.
  ASSERT_TRUE(CheckExtractionSize(**f, allowed).ok());
  core::LocalJobContext cancelled;
  cancelled.Cancel();
  EXPECT_EQ(ExtractCsg(**f, allowed, cancelled).status().code(), absl::StatusCode::kCancelled);
}

// Distance from p to the three quarter circles where the sphere of radius r about the corner
// (h, h, h) of the box [−h, h]³ meets the box's faces.
double DistanceToCornerArcs(const Vec3d& p, double h, double r) {
  const Vec3d c = Vec3d::Constant(h);
  double best = std::numeric_limits<double>::infinity();
  for (int axis = 0; axis < 3; ++axis) {
    Vec3d v = p - c;
    v[axis] = 0;
    const int b = (axis + 1) % 3, e = (axis + 2) % 3;
    if (v.norm() > 0 && v[b] <= 0 && v[e] <= 0) best = std::min(best, (p - (c + r * v.normalized())).norm());
    best = std::min({best, (p - (c - r * Vec3d::Unit(b))).norm(), (p - (c - r * Vec3d::Unit(e))).norm()});
  }
  return best;
}

// The box [−h, h]³ minus the sphere of radius 0.4 about its corner (h, h, h), at cell 1/128.
void ExpectExactVolumeAndCrispArcs(double h) {
  SCOPED_TRACE(core::StrCat("h=", h));
  const double r = 0.4;
  const Solid s =
      Extract(core::StrCat("difference(box(size=", 2 * h, ") sphere(c=", h, ",", h, ",", h, " r=", r, "))"), 1.0 / 128);
  ASSERT_FALSE(s.mesh.faces.empty());
  ExpectClosed(s);
  const double exact = 8 * h * h * h - std::numbers::pi * r * r * r / 6;
  EXPECT_NEAR(s.volume, exact, 2e-4 * exact);
  const double diagonal = std::sqrt(3.0);
  // Every vertex on the true surface.
  double surface = 0;
  for (const auto& v : s.mesh.vertices) {
    const Vec3d x = v.cast<double>();
    Vec3d q = x.cwiseAbs() - Vec3d::Constant(h);
    const double box = q.cwiseMax(0.0).norm() + std::min(q.maxCoeff(), 0.0);
    surface = std::max(surface, std::abs(std::max(box, r - (x - Vec3d::Constant(h)).norm())));
  }
  // The intersection curve: the mesh's edges between faces of the two operands.
  double curve_to_arcs = 0;
  std::vector<std::pair<Vec3d, Vec3d>> curve;
  std::map<std::pair<uint32_t, uint32_t>, int> edge_face;
  std::vector<int> face_operand(s.mesh.faces.size());
  for (size_t f = 0; f < s.mesh.faces.size(); ++f) {
    const auto& t = s.mesh.faces[f];
    const Vec3d centroid = (s.mesh.vertices[t[0]] + s.mesh.vertices[t[1]] + s.mesh.vertices[t[2]]).cast<double>() / 3;
    face_operand[f] = s.function->ActiveOperand(centroid);
    for (int k = 0; k < 3; ++k) {
      const uint32_t a = t[static_cast<size_t>(k)], b = t[static_cast<size_t>((k + 1) % 3)];
      auto [it, fresh] = edge_face.emplace(std::minmax(a, b), static_cast<int>(f));
      if (!fresh && face_operand[static_cast<size_t>(it->second)] != face_operand[f]) {
        const Vec3d pa = s.mesh.vertices[a].cast<double>(), pb = s.mesh.vertices[b].cast<double>();
        curve.emplace_back(pa, pb);
        curve_to_arcs = std::max({curve_to_arcs, DistanceToCornerArcs(pa, h, r), DistanceToCornerArcs(pb, h, r)});
      }
    }
  }
  // And back: every point of the true arcs near a curve edge.
  double arcs_to_curve = 0;
  for (int axis = 0; axis < 3; ++axis) {
    for (int i = 0; i <= 200; ++i) {
      const double phi = std::numbers::pi / 2 * i / 200.0;
      Vec3d p = Vec3d::Constant(h);
      p[(axis + 1) % 3] -= r * std::cos(phi);
      p[(axis + 2) % 3] -= r * std::sin(phi);
      double best = std::numeric_limits<double>::infinity();
      for (const auto& [a, b] : curve) {
        const double t = std::clamp((p - a).dot(b - a) / std::max((b - a).squaredNorm(), 1e-300), 0.0, 1.0);
        best = std::min(best, (p - (a + t * (b - a))).norm());
      }
      arcs_to_curve = std::max(arcs_to_curve, best);
    }
  }
  std::printf("  %zu triangles, volume %.6f (exact %.6f), surface %.2e, curve->arcs %.2e, arcs->curve %.2e (diag)\n",
              s.mesh.faces.size(), s.volume, exact, surface / diagonal, curve_to_arcs / diagonal,
              arcs_to_curve / diagonal);
  EXPECT_LT(surface, 1e-5 * diagonal);
  EXPECT_GT(curve.size(), 100u);
  // Measured 1.1e-5 to 1.9e-5 of the diagonal both ways (below 0.003 of a cell). Before the
  // corners that crease ends cut off were inserted, the bisection of stalled roots and the splits
  // where an end could not be moved onto the crease: 2.0e-4 and 4.3e-4.
  EXPECT_LT(curve_to_arcs, 1e-4 * diagonal);
  EXPECT_LT(arcs_to_curve, 1e-4 * diagonal);
}

TEST(CsgExtraction, BoxMinusSphereHasTheExactVolumeAndCrispArcs) {
  ExpectExactVolumeAndCrispArcs(0.5);  // Box faces on lattice planes: marching meets F = 0 exactly.
  ExpectExactVolumeAndCrispArcs(0.4953);
  ExpectExactVolumeAndCrispArcs(0.4917);
}

TEST(CsgExtraction, UnionIntersectionAndTransformsKeepExactVolumes) {
  // Two unit spheres 1 apart: the lens they share is 5π/12.
  const double lens = 5 * std::numbers::pi / 12, ball = 4 * std::numbers::pi / 3;
  const Solid u = Extract("union(sphere(r=1) sphere(c=1,0,0 r=1))", 1.0 / 32);
  ExpectClosed(u);
  EXPECT_NEAR(u.volume, 2 * ball - lens, 2e-3 * (2 * ball - lens));
  const Solid i = Extract("intersection(sphere(r=1) sphere(c=1,0,0 r=1))", 1.0 / 32);
  ExpectClosed(i);
  EXPECT_NEAR(i.volume, lens, 2e-3 * lens);
  // A drilled, turned and shifted cube: a box minus a through cylinder (genus 1).
  const Solid d =
      Extract("translate(t=3,0,0 rotate(axis=1,1,0 deg=30 difference(box(size=2) cylinder(a=0,0,-2 b=0,0,2 r=0.5))))",
              1.0 / 24);
  ExpectClosed(d, 1);
  EXPECT_NEAR(d.volume, 8 - std::numbers::pi * 0.25 * 2, 1e-3 * 8);
  // A torus scaled by 2 about its centre: volume 2π²Rr² × 8.
  const Solid t = Extract("scale(s=2 c=1,1,1 torus(c=1,1,1 R=1 r=0.3))", 1.0 / 12);
  ExpectClosed(t, 1);
  const double torus = 2 * std::numbers::pi * std::numbers::pi * 1 * 0.09 * 8;
  EXPECT_NEAR(t.volume, torus, 3e-3 * torus);
  // A half-space bounded by a box: half of it.
  const Solid half = Extract("intersection(box(size=1) plane(p=0,0,0.1 n=0,0,1))", 1.0 / 64);
  ExpectClosed(half);
  EXPECT_NEAR(half.volume, 0.6, 1e-4);
}

// A PU function of a sampled sphere as a job operand, cut by a box: the cut face is flat and
// exact, the rest lies on the sphere.
TEST(CsgExtraction, PuOperandsCombineWithPrimitives) {
  const core::PointCloud cloud = testing::SphereCloud(30'000, 1.0);
  core::LocalJobContext ctx;
  auto built = pu::BuildPu(cloud, pu::PuParams{}, ctx);
  ASSERT_TRUE(built.ok()) << built.status();
  // Through the kept bytes, as the service uses it.
  auto function = pu::DeserializePu(pu::SerializePu(**built));
  ASSERT_TRUE(function.ok()) << function.status();
  const Operand operand = jobs::MakePuOperand(*std::move(function));
  int resolved = 0;
  const Solid s = Extract("difference(job:ball box(min=0,-2,-2 max=2,2,2))", 0, [&](const std::string& id) {
    ++resolved;
    EXPECT_EQ(id, "ball");
    return absl::StatusOr<Operand>(operand);
  });
  EXPECT_EQ(resolved, 1);
  ExpectClosed(s);
  const double half_ball = 2 * std::numbers::pi / 3;
  EXPECT_NEAR(s.volume, half_ball, 3e-3 * half_ball);
  double off = 0;
  for (const auto& v : s.mesh.vertices) {
    const Vec3d x = v.cast<double>();
    off = std::max(off, std::abs(std::max(x.norm() - 1, x.x())));
  }
  EXPECT_LT(off, 2e-3);
}

TEST(PuSerialization, RoundTripEvaluatesIdenticallyAndRejectsDamage) {
  const core::PointCloud cloud = testing::TorusCloud(20'000, 1.0, 0.3);
  core::LocalJobContext ctx;
  auto built = pu::BuildPu(cloud, pu::PuParams{}, ctx);
  ASSERT_TRUE(built.ok()) << built.status();
  const std::string bytes = pu::SerializePu(**built);
  EXPECT_TRUE(pu::IsStoredPu(bytes));
  auto back = pu::DeserializePu(bytes);
  ASSERT_TRUE(back.ok()) << back.status();
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(-1.5, 1.5);
  for (int i = 0; i < 2000; ++i) {
    const Vec3d x(u(rng), u(rng), u(rng) * 0.3);
    const core::FieldGradient a = (*built)->ValueAndGradient(x), b = (*back)->ValueAndGradient(x);
    ASSERT_EQ(std::isnan(a.value), std::isnan(b.value));
    if (!std::isnan(a.value)) {
      EXPECT_EQ(a.value, b.value);
    }
    EXPECT_EQ(a.defined, b.defined);
    EXPECT_EQ(a.gradient, b.gradient);
  }
  EXPECT_EQ((*back)->stats().mean_spacing, (*built)->stats().mean_spacing);
  // Truncations and a corrupted index are refused, never read.
  for (size_t cut : {size_t{0}, size_t{7}, bytes.size() / 3, bytes.size() - 1}) {
    EXPECT_EQ(pu::DeserializePu(bytes.substr(0, cut)).status().code(), absl::StatusCode::kInvalidArgument) << cut;
  }
  // Damage anywhere either is refused or leaves a function that evaluates inside its arrays
  // (the sanitizer build checks the latter); indices and counts out of range are refused.
  int refused = 0;
  for (size_t at = 8; at + 8 < bytes.size(); at += bytes.size() / 97) {
    std::string damaged = bytes;
    for (size_t i = at; i < at + 8; ++i) damaged[i] = '\xff';
    auto f = pu::DeserializePu(damaged);
    if (!f.ok()) {
      ++refused;
      continue;
    }
    for (int i = 0; i < 50; ++i) (void)(*f)->ValueAndGradient(Vec3d(u(rng), u(rng), u(rng) * 0.3));
  }
  EXPECT_GT(refused, 5);
}

}  // namespace
}  // namespace lsqsurf::csg
