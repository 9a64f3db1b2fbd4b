// Tiled PU: forced into many small tiles, a build gives the untiled surface of the same frame,
// face for face, and the welded mesh is closed across every seam.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>

#include "absl/container/flat_hash_map.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/core/kd_tree.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/surface_distance.h"
#include "worker/pu/pu.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::pu {
namespace {

struct Runs {
  core::TriangleMesh whole, tiled;
  TiledStats stats;
  double diagonal = 0;
};

Runs RunBoth(const core::PointCloud& cloud, const PuExtractParams& extract, const PuTileParams& tiles) {
  Runs runs;
  core::LocalJobContext ctx;
  MeshSink sink;
  auto tiled = ReconstructTiled(CloudSource(cloud, 7000), PuParams{}, extract, tiles, sink, ctx);
  EXPECT_TRUE(tiled.ok()) << tiled.status();
  if (!tiled.ok()) return runs;
  runs.stats = *tiled;
  runs.tiled = std::move(sink.mesh());
  EXPECT_EQ(static_cast<int64_t>(runs.tiled.faces.size()), runs.stats.faces);
  runs.diagonal = runs.stats.frame.diagonal;
  // The same frame, untiled.
  auto function = BuildPuInFrame(cloud, runs.stats.frame, nullptr, ctx);
  EXPECT_TRUE(function.ok()) << function.status();
  if (!function.ok()) return runs;
  auto whole = Extract(**function, extract, ctx);
  EXPECT_TRUE(whole.ok()) << whole.status();
  if (whole.ok()) runs.whole = std::move(whole->mesh);
  std::printf(
      "  %zu points: %lld tiles at level %d (largest %lld points, margin %.3g), %zu / %zu faces, %lld seam "
      "vertices\n",
      cloud.size(), static_cast<long long>(runs.stats.tiles), runs.stats.tile_level,
      static_cast<long long>(runs.stats.largest_tile), runs.stats.margin, runs.tiled.faces.size(),
      runs.whole.faces.size(), static_cast<long long>(runs.stats.seam_vertices));
  return runs;
}

// Every vertex of `b` within `tolerance` of one of `a`, one to one, and the faces the same triples.
void ExpectSameMesh(const core::TriangleMesh& a, const core::TriangleMesh& b, double tolerance) {
  ASSERT_EQ(a.vertices.size(), b.vertices.size());
  ASSERT_EQ(a.faces.size(), b.faces.size());
  core::KdTree index(a.vertices);
  std::vector<uint32_t> to_a(b.vertices.size());
  std::vector<char> used(a.vertices.size(), 0);
  double worst = 0;
  for (size_t v = 0; v < b.vertices.size(); ++v) {
    const core::Neighbor n = index.Nearest(b.vertices[v]);
    worst = std::max(worst, static_cast<double>(std::sqrt(n.distance2)));
    to_a[v] = n.index;
    EXPECT_FALSE(used[n.index]) << "two vertices near vertex " << n.index;
    used[n.index] = 1;
  }
  EXPECT_LE(worst, tolerance);
  auto sorted = [](core::Triangle t) {
    // The same triangle up to a rotation of its corners (orientation kept).
    const auto first = std::min_element(t.begin(), t.end()) - t.begin();
    std::rotate(t.begin(), t.begin() + first, t.end());
    return t;
  };
  std::vector<core::Triangle> fa, fb;
  for (const core::Triangle& t : a.faces) fa.push_back(sorted(t));
  for (core::Triangle t : b.faces) {
    for (uint32_t& v : t) v = to_a[v];
    fb.push_back(sorted(t));
  }
  std::sort(fa.begin(), fa.end());
  std::sort(fb.begin(), fb.end());
  EXPECT_TRUE(fa == fb) << "the tiled faces are not the untiled ones";
}

void ExpectClosed(const core::TriangleMesh& mesh, int euler) {
  const core::MeshTopology welded = core::AnalyzeTopology(core::WeldByPosition(mesh));
  EXPECT_TRUE(welded.watertight());
  EXPECT_TRUE(welded.consistently_oriented());
  EXPECT_EQ(welded.components, 1);
  EXPECT_EQ(welded.euler_characteristic(), euler);
}

PuExtractParams RawMarching() {
  PuExtractParams extract;
  extract.marching.relax_steps = 0;
  extract.marching.crease_angle = 0;
  return extract;
}

TEST(PuTiles, ASphereInManyTilesIsTheUntiledSphere) {
  const core::PointCloud cloud = testing::SphereCloud(20'000);
  const Runs raw = RunBoth(cloud, RawMarching(), {.tile_points = 4'000, .support_cap = 16});
  EXPECT_EQ(raw.stats.tiles, 8);
  ExpectSameMesh(raw.whole, raw.tiled, 1e-9 * raw.diagonal);
  ExpectClosed(raw.tiled, 2);
  // Finished per tile, the seams fixed: still closed, the same surface.
  const Runs finished = RunBoth(cloud, PuExtractParams{}, {.tile_points = 4'000, .support_cap = 16});
  ExpectClosed(finished.tiled, 2);
  EXPECT_EQ(finished.tiled.faces.size(), finished.whole.faces.size());
  double worst = 0;
  for (const core::Vec3f& v : finished.tiled.vertices) worst = std::max(worst, std::abs(v.cast<double>().norm() - 1));
  EXPECT_LT(worst, 1e-3);
}

// The steps run apart, as servers run them: the plan travels as bytes, the tiles run in reverse
// order from their points alone, each with a fresh context, and their parts are joined in the
// plan's order. The surface is the one-process build's.
TEST(PuTiles, TilesRunApartAndJoinedAreTheTiledSurface) {
  const core::PointCloud cloud = testing::SphereCloud(20'000);
  const PuTileParams tiles{.tile_points = 4'000, .support_cap = 16};
  const PuExtractParams extract;
  core::LocalJobContext ctx;
  MeshSink whole;
  auto built = ReconstructTiled(CloudSource(cloud, 5000), PuParams{}, extract, tiles, whole, ctx);
  ASSERT_TRUE(built.ok()) << built.status();

  auto planned = PlannedCloud::Plan(CloudSource(cloud, 5000), PuParams{}, extract, tiles, ctx);
  ASSERT_TRUE(planned.ok()) << planned.status();
  auto plan = DecodeTilePlan(EncodeTilePlan((*planned)->plan()));
  ASSERT_TRUE(plan.ok()) << plan.status();
  ASSERT_EQ(plan->tiles, (*planned)->plan().tiles);
  std::vector<std::string> parts(plan->tiles.size());
  for (size_t t = plan->tiles.size(); t-- > 0;) {
    auto points = (*planned)->TilePoints(t);
    ASSERT_TRUE(points.ok()) << points.status();
    core::LocalJobContext tile_ctx;
    auto bytes = DecodeTilePoints(EncodeTilePoints(*points));
    ASSERT_TRUE(bytes.ok()) << bytes.status();
    ASSERT_EQ(bytes->positions, points->positions);
    auto part = RunTile(*plan, t, *std::move(bytes), tile_ctx);
    ASSERT_TRUE(part.ok()) << part.status();
    parts[t] = *std::move(part);
  }
  MeshSink joined;
  TileJoiner joiner(*plan, joined);
  // Out of order, cut short or not a part at all: refused, and the joiner still takes the right one.
  ASSERT_GT(parts.size(), 1u);
  EXPECT_EQ(joiner.Add(parts[1]).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(joiner.Add(parts[0].substr(0, parts[0].size() - 3)).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(joiner.Add(EncodeTilePlan(*plan)).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(DecodeTilePlan(parts[0]).ok());
  for (size_t t = 0; t + 1 < parts.size(); ++t) ASSERT_TRUE(joiner.Add(parts[t]).ok()) << t;
  EXPECT_EQ(TileJoiner(*plan, joined).Finish().status().code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(joiner.Add(parts.back()).ok());
  auto stats = joiner.Finish();
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->tiles, built->tiles);
  EXPECT_EQ(stats->seam_vertices, built->seam_vertices);
  EXPECT_EQ(stats->fit.noise_estimate, built->fit.noise_estimate);
  // The extractor's threads may order a tile's vertices differently from run to run.
  ExpectSameMesh(whole.mesh(), joined.mesh(), 1e-9 * plan->frame.diagonal);
  ExpectClosed(joined.mesh(), 2);
}

// A CAD part longer than its margins: the tiles at one end never see the other end's points.
TEST(PuTiles, ALongDrilledBlockInManyTilesIsTheUntiledBlock) {
  const core::PointCloud cloud = testing::DrilledBlockCloud(30'000, 4.0, 0.6, 0.3, 0.3);
  const Runs raw = RunBoth(cloud, RawMarching(), {.tile_points = 5'000, .support_cap = 16});
  EXPECT_GE(raw.stats.tiles, 8);
  EXPECT_LT(raw.stats.largest_tile, static_cast<int64_t>(cloud.size()));
  ExpectSameMesh(raw.whole, raw.tiled, 1e-9 * raw.diagonal);
  ExpectClosed(raw.tiled, 0);
  const Runs finished = RunBoth(cloud, PuExtractParams{}, {.tile_points = 5'000, .support_cap = 16});
  ExpectClosed(finished.tiled, 0);
  EXPECT_NEAR(core::EnclosedVolume(finished.tiled), core::EnclosedVolume(finished.whole),
              1e-4 * core::EnclosedVolume(finished.whole));
}

// The finished surfaces (creases split, relaxed, holes closed) tiled and untiled: the same
// closedness and pieces once welded by position, vertex counts within 0.5 %, and the two surfaces
// within `apart` of each other (mean both ways, shares of the diagonal). Relaxation holds a tile's
// border vertices where they were marched, so the two are alike rather than equal (a sphere's
// 20k points in 8 tiles: 2.2e-6 apart).
void ExpectSameSurface(const Runs& runs, double apart) {
  const core::MeshTopology whole = core::AnalyzeTopology(core::WeldByPosition(runs.whole));
  const core::MeshTopology tiled = core::AnalyzeTopology(core::WeldByPosition(runs.tiled));
  EXPECT_EQ(tiled.watertight(), whole.watertight());
  EXPECT_EQ(tiled.boundary_edges, whole.boundary_edges);
  EXPECT_EQ(tiled.components, whole.components);
  EXPECT_EQ(tiled.euler_characteristic(), whole.euler_characteristic());
  const double ratio = static_cast<double>(tiled.vertices) / static_cast<double>(whole.vertices);
  EXPECT_NEAR(ratio, 1.0, 5e-3);
  core::LocalJobContext ctx;
  auto cmp = core::CompareMeshes(runs.whole, runs.tiled, {.samples = 200'000}, ctx);
  ASSERT_TRUE(cmp.ok()) << cmp.status();
  std::printf(
      "  finished: vertices %.4f of the untiled, %lld components, Euler characteristic %lld; apart: %.3g and %.3g "
      "(means), %.3g (Hausdorff)\n",
      ratio, static_cast<long long>(tiled.components), static_cast<long long>(tiled.euler_characteristic()),
      cmp->mean_ref_to_cand, cmp->mean_cand_to_ref, cmp->hausdorff);
  EXPECT_LT(cmp->mean_ref_to_cand, apart);
  EXPECT_LT(cmp->mean_cand_to_ref, apart);
}

PuExtractParams ClosingHoles(PuExtractParams extract) {
  extract.max_hole_edges = 32;  // The surface job's.
  return extract;
}

// A hole of a few edges across a seam (points taken away over a small cap where tiles meet) is
// closed once the tiles are welded, as the untiled surface closes it.
TEST(PuTiles, ASmallHoleAcrossASeamClosesAsUntiled) {
  core::PointCloud cloud = testing::SphereCloud(20'000);
  core::PointCloud holed;
  const core::Vec3d at = core::Vec3d(1, 0.02, -0.03).normalized();
  const double radius = 0.18;  // 7 spacings: the fits no longer cover it.
  for (size_t i = 0; i < cloud.size(); ++i) {
    if ((cloud.positions[i].cast<double>() - at).norm() < radius) continue;
    holed.positions.push_back(cloud.positions[i]);
    holed.normals.push_back(cloud.normals[i]);
  }
  const PuTileParams tiles{.tile_points = 4'000, .support_cap = 16};
  const Runs open = RunBoth(holed, {}, tiles);
  const core::MeshTopology left = core::AnalyzeTopology(core::WeldByPosition(open.tiled));
  std::printf("  %lld boundary edges left open\n", static_cast<long long>(left.boundary_edges));
  EXPECT_GT(left.boundary_edges, 0) << "no hole to close";
  EXPECT_LE(left.boundary_edges, 32);
  EXPECT_EQ(core::AnalyzeTopology(core::WeldByPosition(open.whole)).boundary_edges, left.boundary_edges);
  // The hole reaches across the planes where the tiles meet (the root cube's middle, 8 tiles).
  ASSERT_EQ(open.stats.tile_level, 1);
  const core::Vec3d middle = open.stats.frame.origin + core::Vec3d::Constant(open.stats.frame.root_edge / 2);
  EXPECT_LT(std::abs(at.y() - middle.y()), radius);
  EXPECT_LT(std::abs(at.z() - middle.z()), radius);
  const Runs closed = RunBoth(holed, ClosingHoles({}), tiles);
  ExpectClosed(closed.tiled, 2);
  ExpectSameSurface(closed, 1e-5);
}

// The frame's noise is the median of the tiles' estimates: on a noisy sphere it is the untiled
// estimate's, the effective parameters follow it, and the tiles still close.
TEST(PuTiles, ANoisySphereGetsTheNoiseOfTheWholeCloud) {
  core::PointCloud cloud = testing::SphereCloud(20'000);
  std::mt19937_64 rng(3);
  const double sigma = 0.004;  // 0.12 % of the diagonal (2 sqrt 3).
  std::normal_distribution<double> noise(0, sigma);
  for (size_t i = 0; i < cloud.size(); ++i) {
    cloud.positions[i] += (noise(rng) * cloud.normals[i].cast<double>()).cast<float>();
  }
  core::LocalJobContext ctx;
  auto whole = BuildPu(cloud, PuParams{}, ctx);
  ASSERT_TRUE(whole.ok()) << whole.status();
  MeshSink sink;
  auto tiled = ReconstructTiled(CloudSource(cloud), PuParams{}, PuExtractParams{}, {.tile_points = 4'000}, sink, ctx);
  ASSERT_TRUE(tiled.ok()) << tiled.status();
  const double truth = sigma / tiled->frame.diagonal;
  std::printf("  noise: true %.3g, untiled %.3g, tiled %.3g; threshold %.3g\n", truth, (*whole)->stats().noise_estimate,
              tiled->frame.noise_estimate, tiled->frame.params.error_threshold);
  EXPECT_NEAR(tiled->frame.noise_estimate, (*whole)->stats().noise_estimate, 0.15 * truth);
  EXPECT_NEAR(tiled->frame.noise_estimate, truth, 0.3 * truth);
  EXPECT_EQ(tiled->frame.params.error_threshold, 3 * tiled->frame.noise_estimate);
  EXPECT_NEAR(tiled->frame.mean_spacing, (*whole)->stats().mean_spacing, 0.03 * (*whole)->stats().mean_spacing);
  EXPECT_GE(tiled->tiles, 8);
  ExpectClosed(sink.mesh(), 2);
}

}  // namespace
}  // namespace lsqsurf::pu

namespace lsqsurf::pu {
namespace {

// A process id that was alive a moment ago and is not now.
pid_t DeadPid() {
  const pid_t child = fork();
  if (child == 0) _exit(0);
  int status = 0;
  waitpid(child, &status, 0);
  return child;
}

TEST(TiledScratch, OnlyTheDirectoriesOfDeadProcessesAreSwept) {
  const std::filesystem::path parent = testing::FreshTestDir("tiled-scratch");
  const auto made = [&](const std::string& name) {
    std::filesystem::create_directories(parent / name);
    std::ofstream(parent / name / "points") << "left behind";
    return parent / name;
  };
  const auto dead = made("lsqsurf-tiles-" + std::to_string(DeadPid()) + "-Ab12Cd");
  const auto alive = made("lsqsurf-tiles-" + std::to_string(getpid()) + "-Ef34Gh");
  const auto other = made("not-a-scratch-dir");
  auto swept = SweepAbandonedScratch(parent.string());
  ASSERT_TRUE(swept.ok()) << swept.status();
  EXPECT_EQ(*swept, 1);
  EXPECT_FALSE(std::filesystem::exists(dead));
  EXPECT_TRUE(std::filesystem::exists(alive / "points"));
  EXPECT_TRUE(std::filesystem::exists(other / "points"));
  EXPECT_EQ(SweepAbandonedScratch((parent / "missing").string()).status().code(), absl::StatusCode::kUnavailable);
  // A tiled build's own directory is named for this process, and goes with the build.
  const core::PointCloud sphere = testing::SphereCloud(6000);
  MeshSink sink;
  PuTileParams tiles;
  tiles.tile_points = 2000;
  core::LocalJobContext ctx;
  auto built = ReconstructTiled(CloudSource(sphere), PuParams{}, PuExtractParams{}, tiles, sink, ctx, parent.string());
  ASSERT_TRUE(built.ok()) << built.status();
  EXPECT_GT(built->tiles, 1);
  size_t entries = 0;
  for (const auto& entry : std::filesystem::directory_iterator(parent)) entries += entry.exists();
  EXPECT_EQ(entries, 2u);  // alive and other.
  std::filesystem::remove_all(parent);
}

}  // namespace
}  // namespace lsqsurf::pu
