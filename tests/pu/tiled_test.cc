// Tiled PU: forced into many small tiles, a build gives the untiled surface of the same frame,
// face for face, and the welded mesh is closed across every seam.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>

#include "absl/container/flat_hash_map.h"
#include "tests/pu/tiled_compare.h"
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/core/kd_tree.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/surface_distance.h"
#include "worker/pu/pu.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::pu {
namespace {

using compare::ClosingHoles;
using compare::ExpectClosed;
using compare::ExpectSameMesh;
using compare::ExpectSameSurface;
using compare::RawMarching;
using compare::RunBoth;
using compare::Runs;

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

// A single view's open sheet, longer than the margins, forced into many tiles: its rim, where F's
// reach is short (the points lie to one side there), crosses the tiles, and each tile reads
// enough around its cube to judge it as the untiled build does, so the sheet ends where the
// untiled one ends.
TEST(PuTiles, AnOpenSheetInManyTilesEndsAtTheUntiledRim) {
  const core::PointCloud cloud = testing::WavyStripCloud(30'000, 4.0, 0.6);
  const PuTileParams tiles{.tile_points = 3'000, .support_cap = 16};
  const Runs raw = RunBoth(cloud, RawMarching(), tiles);
  EXPECT_GE(raw.stats.tiles, 6);
  EXPECT_LT(raw.stats.largest_tile, static_cast<int64_t>(cloud.size()));
  ExpectSameMesh(raw.whole, raw.tiled, 1e-9 * raw.diagonal);
  const core::MeshTopology sheet = core::AnalyzeTopology(core::WeldByPosition(raw.tiled));
  EXPECT_EQ(sheet.components, 1);
  EXPECT_EQ(sheet.boundary_loops, 1);  // The rim, and no seam left open.
  EXPECT_EQ(sheet.non_manifold_edges, 0);
  ExpectSameSurface(RunBoth(cloud, PuExtractParams{}, tiles), 1e-5);
}

// A hole of a few edges across a seam (points taken away over a small cap where tiles meet) is
// closed once the tiles are welded, as the untiled surface closes it.
TEST(PuTiles, ASmallHoleAcrossASeamClosesAsUntiled) {
  core::PointCloud cloud = testing::SphereCloud(20'000);
  core::PointCloud holed;
  const core::Vec3d at = core::Vec3d(1, 0.02, -0.03).normalized();
  const double radius = 0.13;  // 5 spacings: the fits no longer cover it.
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

// An untiled build's frame (MeasureFrame, in memory) is the one a plan fixes when the cloud fits
// one tile, and a plan of many tiles measures the same spacing and root cube.
TEST(PuTiles, TheUntiledFrameIsTheOneTilePlansFrame) {
  const core::PointCloud cloud = testing::DrilledBlockCloud(30'000, 2.0, 0.6, 0.3, 0.3);
  core::LocalJobContext ctx;
  auto frame = MeasureFrame(cloud, PuParams{}, PuExtractParams{}, PuTileParams{}, ctx);
  ASSERT_TRUE(frame.ok()) << frame.status();
  auto one = PlannedCloud::Plan(CloudSource(cloud, 7000), PuParams{}, PuExtractParams{}, PuTileParams{}, ctx);
  ASSERT_TRUE(one.ok()) << one.status();
  ASSERT_EQ((*one)->plan().tiles.size(), 1u);
  const PuFrame& planned = (*one)->plan().frame;
  EXPECT_EQ(frame->origin, planned.origin);
  EXPECT_EQ(frame->root_edge, planned.root_edge);
  EXPECT_EQ(frame->diagonal, planned.diagonal);
  EXPECT_EQ(frame->mean_spacing, planned.mean_spacing);
  EXPECT_EQ(frame->noise_estimate, planned.noise_estimate);
  EXPECT_EQ(frame->max_support, planned.max_support);
  EXPECT_EQ(frame->params.error_threshold, planned.params.error_threshold);
  EXPECT_EQ(frame->params.min_points, planned.params.min_points);
  auto many = PlannedCloud::Plan(CloudSource(cloud, 7000), PuParams{}, PuExtractParams{},
                                 {.tile_points = 4'000, .support_cap = 64}, ctx);
  ASSERT_TRUE(many.ok()) << many.status();
  EXPECT_GE((*many)->plan().tiles.size(), 8u);
  EXPECT_EQ((*many)->plan().frame.root_edge, frame->root_edge);
  EXPECT_NEAR((*many)->plan().frame.mean_spacing, frame->mean_spacing, 1e-3 * frame->mean_spacing);
  EXPECT_NEAR((*many)->plan().frame.max_support, frame->max_support, 1e-3 * frame->max_support);
}

// The error threshold follows the sampling on clouds denser than it: at most threshold_spacings
// mean spacings (as a share of the diagonal), in a plan of one tile as in one of many; a cloud
// coarser than that keeps error_threshold, and threshold_spacings = 0 keeps it at any density.
TEST(PuTiles, ADenseCloudsThresholdFollowsItsSpacing) {
  const core::PointCloud cloud = testing::SphereCloud(20'000);
  core::LocalJobContext ctx;
  PuParams fit;
  fit.noise_level = 0;  // Exact data: the noise adjustment stays out of it.
  auto frame_with = [&](double threshold_spacings, int64_t tile_points) -> absl::StatusOr<PuFrame> {
    const PuTileParams tiles{.tile_points = tile_points, .support_cap = 64, .threshold_spacings = threshold_spacings};
    if (tile_points >= static_cast<int64_t>(cloud.size())) return MeasureFrame(cloud, fit, {}, tiles, ctx);
    auto planned = PlannedCloud::Plan(CloudSource(cloud, 7000), fit, {}, tiles, ctx);
    if (!planned.ok()) return planned.status();
    return (*planned)->plan().frame;
  };
  auto sparse = frame_with(PuTileParams{}.threshold_spacings, 1'000'000);
  ASSERT_TRUE(sparse.ok()) << sparse.status();
  const double spacing = sparse->mean_spacing / sparse->diagonal;  // About 3.6e-3 of the diagonal.
  ASSERT_GT(PuTileParams{}.threshold_spacings * spacing, fit.error_threshold) << "the sphere is too dense for this";
  EXPECT_EQ(sparse->params.error_threshold, fit.error_threshold);
  // A tenth of the default threshold in spacings makes this cloud "dense".
  const double dense_factor = 0.1 * fit.error_threshold / spacing;
  auto dense = frame_with(dense_factor, 1'000'000);
  ASSERT_TRUE(dense.ok()) << dense.status();
  // The bound, rounded down to a step of 1/16 octave.
  const double bound = dense_factor * dense->mean_spacing / dense->diagonal;
  EXPECT_LE(dense->params.error_threshold, bound * (1 + 1e-12));
  EXPECT_GT(dense->params.error_threshold, bound * std::exp2(-1.0 / 16));
  EXPECT_NEAR(dense->params.error_threshold, 0.1 * fit.error_threshold, 0.01 * fit.error_threshold);
  auto tiled = frame_with(dense_factor, 4'000);
  ASSERT_TRUE(tiled.ok()) << tiled.status();
  EXPECT_EQ(tiled->params.error_threshold, dense->params.error_threshold);  // Whatever the cut.
  EXPECT_NE(tiled->mean_spacing, dense->mean_spacing);                      // Though it moves the spacing.
  auto off = frame_with(0, 1'000'000);
  ASSERT_TRUE(off.ok()) << off.status();
  EXPECT_EQ(off->params.error_threshold, fit.error_threshold);
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
