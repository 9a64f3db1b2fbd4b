#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/front/front_internal.h"
#include "worker/front/front_tracking.h"

namespace lsqsurf::front {
namespace {

// Adds each candidate as a marker born at `step` unless a marker facing the same way (in `grid`,
// which the new ones join) lies within `spacing` of it.
void AddMarkersApart(std::span<const Crossing> candidates, double spacing, int step, SpacingGrid& grid, Markers& m) {
  for (const Crossing& c : candidates) {
    if (grid.HasNear(c.point, c.normal, spacing)) continue;
    grid.Add(c.point, c.normal);
    m.front.points.push_back(c.point);
    m.front.normals.push_back(c.normal);
    m.birth.push_back(step);
  }
}

}  // namespace

// Drops every marker that an older (or, at equal age, earlier) kept marker facing the same way
// lies within `min_distance` of.
void ThinMarkers(Markers& m, double min_distance) {
  std::vector<uint32_t> order(m.front.points.size());
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return m.birth[a] < m.birth[b]; });
  SpacingGrid kept(min_distance);
  std::vector<char> keep(order.size(), 0);
  for (uint32_t i : order) {
    if (kept.HasNear(m.front.points[i], m.front.normals[i], min_distance)) continue;
    kept.Add(m.front.points[i], m.front.normals[i]);
    keep[i] = 1;
  }
  Markers out;
  for (size_t i = 0; i < keep.size(); ++i) {
    if (!keep[i]) continue;
    out.front.points.push_back(m.front.points[i]);
    out.front.normals.push_back(m.front.normals[i]);
    out.birth.push_back(m.birth[i]);
  }
  m = std::move(out);
}

// Where the flow has stretched the markers apart, adds new ones. The midpoint of two markers
// facing the same way (within 60°) and at most 2h apart, with no marker facing that way within
// `gap` of it, is projected onto the RAMLS surface fitted to that side alone (the markers facing
// within 90° of the pair), so the two faces of a sheet never mix however thin it is. Midpoints
// only interpolate: a spot beyond the last marker, at a sheet's rim, is never made up. A
// projection that does not settle on the surface within h/2 is dropped.
absl::Status FillGaps(Markers& m, int step, double h, double gap, double support_factor, core::JobContext& ctx) {
  constexpr int kProjections = 3;
  constexpr double kPairCosine = 0.5;
  const double reach = 2 * h;
  auto field = FrontFunction(m.front, h, support_factor, ctx);
  if (!field.ok()) return field.status();
  const core::KdTree tree(m.front.points);
  SpacingGrid grid(gap);
  for (size_t i = 0; i < m.front.points.size(); ++i) grid.Add(m.front.points[i], m.front.normals[i]);
  const size_t n = m.front.points.size();
  std::vector<std::vector<Crossing>> spots(n);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 256,
      [&](size_t b, size_t e) {
        std::vector<core::Neighbor> near;
        for (size_t i = b; i < e; ++i) {
          const Vec3f& pi = m.front.points[i];
          const Vec3f& ni = m.front.normals[i];
          tree.Radius(pi, static_cast<float>(reach), near);
          for (const core::Neighbor& q : near) {
            if (q.index <= i || q.distance2 < 4 * gap * gap) continue;
            const Vec3f& nj = m.front.normals[q.index];
            if (ni.dot(nj) < kPairCosine) continue;
            const Vec3d mid = 0.5 * (pi + m.front.points[q.index]).cast<double>();
            const Vec3d facing = (ni + nj).cast<double>().normalized();
            if (grid.HasNear(mid.cast<float>(), facing.cast<float>(), gap)) continue;
            Vec3d x = mid;
            core::FieldGradient g;
            bool ok = true;
            for (int it = 0; it <= kProjections && ok; ++it) {
              g = (*field)->ValueAndGradientFacing(x, facing, 0.0);
              const double g2 = g.gradient.squaredNorm();
              ok = g.defined && g2 > 0;
              if (ok && it < kProjections) x -= g.value / g2 * g.gradient;
            }
            if (!ok || !x.allFinite() || std::abs(g.value) > 1e-3 * h || (x - mid).norm() > 0.5 * h) continue;
            const Vec3d fitted = g.gradient.normalized();
            if (fitted.dot(facing) < kPairCosine) continue;  // The fit turned away from its own side.
            spots[i].push_back({x.cast<float>(), fitted.cast<float>()});
          }
        }
      },
      &ctx));
  for (const std::vector<Crossing>& around : spots) AddMarkersApart(around, gap, step, grid, m);
  return absl::OkStatus();
}

// The markers mode's topology changes: the markers where the blend of TopologyField changes F
// (two sides within the blend radius of each other, or one front inside another) go, and the
// gridline roots of the blended F around them, thinned against the markers that stay, take
// their place.
absl::Status ReplaceMergingMarkers(Markers& m, int step, double h, double support_factor, double merge_distance,
                                   std::vector<bool>& marks, core::JobContext& ctx) {
  auto fit = FrontFunction(m.front, h, support_factor, ctx);
  if (!fit.ok()) return fit.status();
  const TopologyField field(*std::move(fit), 2 * merge_distance * h);
  std::vector<char> merging(m.front.points.size(), 0);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      merging.size(), 512,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) merging[i] = field.BlendActsAt(m.front.points[i].cast<double>());
      },
      &ctx));
  std::vector<Vec3f> replaced;
  Markers kept;
  for (size_t i = 0; i < merging.size(); ++i) {
    if (merging[i]) {
      replaced.push_back(m.front.points[i]);
      continue;
    }
    kept.front.points.push_back(m.front.points[i]);
    kept.front.normals.push_back(m.front.normals[i]);
    kept.birth.push_back(m.birth[i]);
  }
  if (replaced.empty()) return absl::OkStatus();
  const double fine = 0.5 * h;
  auto sampled = SampleGridlines(field, NodesNear(replaced, fine, marks), fine, false, ctx);
  if (!sampled.ok()) return sampled.status();
  SpacingGrid grid(0.5 * h);
  for (size_t i = 0; i < kept.front.points.size(); ++i) grid.Add(kept.front.points[i], kept.front.normals[i]);
  AddMarkersApart(sampled->crossings, 0.5 * h, step, grid, kept);
  m = std::move(kept);
  return absl::OkStatus();
}

}  // namespace lsqsurf::front
