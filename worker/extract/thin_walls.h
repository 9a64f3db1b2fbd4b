// worker/extract/thin_walls.h — probes that keep the lattice from missing walls and gaps
// thinner than a leaf.
//
// A tetrahedron that a wall thinner than itself passes through with every corner outside misses
// the wall, and a hole opens through it (a plate 0.2 % of its diagonal thick, turned off the axes,
// came out of iaMLS in 8 pieces); across a gap as narrow, every corner inside, the two sides
// fuse. Where an oriented point has points near it that face against it, the other sheet lies at
// the median distance along its normal: behind it for a wall, in front of it for a gap. The point
// halfway is a probe (J1aIsosurfaceParams::probes) that the extractor checks against its lattice.
#pragma once

#include <span>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/extract/j1a_isosurface.h"

namespace lsqsurf::extract {

// Two sheets face apart (a wall) or against each other (a gap) when their normals are more than
// 162° apart. PU's wall zones judge them alike.
inline constexpr double kWallFacingCosine = -0.95;
// Walls thinner than this share of a leaf can be missed: J1a's tetrahedra have edges of 0.5 to
// 0.87 leaf edges, so thicker ones hold a lattice vertex wherever they pass.
inline constexpr double kWallLeafShare = 0.8;

struct ThinWallParams {
  // Only walls and gaps thinner than this share of a leaf get probes.
  double max_leaf_share = kWallLeafShare;
  // Nor those thinner than this share: along the normal, points of one noisy sheet whose normals
  // flip lie that close to each other.
  double min_leaf_share = 0.1;
  // The far sheet's offsets may spread over at most this share of the thickness between their
  // quartiles. On a clean plate they are one number, and across a finger only the points nearly
  // opposite face against each other; where noise spreads them wider, the lattice cannot follow
  // the wall everywhere, so splits are only worth their cost where walls are most of the shape
  // (kNoisyWallSpread).
  double max_spread = 0.25;
};

// max_spread for clouds that are mostly noisy walls: noise σ up to about 3/4 of the thickness
// (quartiles 1.35 σ apart). The 0.2 %-thick plate turned off the axes at σ = 0.1 % came out of
// iaMLS in 44 pieces without probes.
inline constexpr double kNoisyWallSpread = 1.0;

// One probe per point that has a wall or gap within reach: the points within max_leaf_share ×
// leaf_edge whose normals face more than 162° away from its own (at least 3 of them, and a tenth
// of those within reach) lie at a median distance along its normal between the two shares of
// `leaf_edge`, their quartiles within max_spread of it. The thickness and the middle are measured
// from the median offsets of both sheets, so that the point's own noise does not move them. Errors:
// kInvalidArgument (no normal per point, a leaf edge that is not a positive number), kCancelled.
// Cost: a kd-tree and a radius query per 16th point; where one of those finds a wall or gap, one
// per point.
absl::StatusOr<std::vector<SideProbe>> ThinWallProbes(std::span<const core::Vec3f> points,
                                                      std::span<const core::Vec3f> normals, double leaf_edge,
                                                      const ThinWallParams& params, core::JobContext& ctx);

}  // namespace lsqsurf::extract
