// tests/pu/tiled_compare.h — a cloud built tiled and untiled in one frame, and the checks that
// the two surfaces are one.
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include "worker/core/kd_tree.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/surface_distance.h"
#include "worker/pu/pu.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::pu::compare {

struct Runs {
  core::TriangleMesh whole, tiled;
  TiledStats stats;
  double diagonal = 0;
};

inline Runs RunBoth(const core::PointCloud& cloud, const PuExtractParams& extract, const PuTileParams& tiles) {
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
inline void ExpectSameMesh(const core::TriangleMesh& a, const core::TriangleMesh& b, double tolerance) {
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

inline void ExpectClosed(const core::TriangleMesh& mesh, int euler) {
  const core::MeshTopology welded = core::AnalyzeTopology(core::WeldByPosition(mesh));
  EXPECT_TRUE(welded.watertight());
  EXPECT_TRUE(welded.consistently_oriented());
  EXPECT_EQ(welded.components, 1);
  EXPECT_EQ(welded.euler_characteristic(), euler);
}

inline PuExtractParams RawMarching() {
  PuExtractParams extract;
  extract.marching.relax_steps = 0;
  extract.marching.crease_angle = 0;
  return extract;
}

// The finished surfaces (creases split, relaxed, holes closed) tiled and untiled: the same
// closedness and pieces once welded by position, vertex counts within 0.5 %, and the two surfaces
// within `apart` of each other (mean both ways, shares of the diagonal). Relaxation holds a tile's
// border vertices where they were marched, so the two are alike rather than equal (a sphere's
// 20k points in 8 tiles: 2.2e-6 apart).
inline void ExpectSameSurface(const Runs& runs, double apart) {
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

inline PuExtractParams ClosingHoles(PuExtractParams extract) {
  extract.max_hole_edges = 32;  // The surface job's.
  return extract;
}

}  // namespace lsqsurf::pu::compare
