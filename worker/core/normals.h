// worker/core/normals.h — normals for point clouds that arrive without them.
//
// Hoppe, DeRose, Duchamp, McDonald, Stuetzle, "Surface reconstruction from unorganized points",
// SIGGRAPH 1992: the normal of each point is the least-variance direction of its k nearest
// neighbours (PCA). Where those k do not lie flat (noise, or the far side of a thin tube closer
// than them), k is chosen among `neighbors` × 1, 2, 4, … (`scales` sizes) as the one whose
// neighbourhood is flattest (least λ₀ / (λ₀ + λ₁ + λ₂), as in Pauly, Gross and Kobbelt 2002):
// noise flattens out in a larger one, while near creases and tight bends the smaller one stays
// flatter. Signs are made consistent by walking a minimum spanning tree of the neighbourhood
// graph with edge cost 1 − |n_i · n_j|, so that orientation crosses flat regions first and sharp
// bends last. Where a wall (or a slot) is thinner than the spacing, a point's neighbours hold both
// layers: steps between the layers flip the sign instead of copying it, points where the layers
// meet are reached last, and three passes let each point's trusted steps outvote the one step
// that reached it. Each connected part is finally turned outward: the sign that
// makes Σ (p_i − centroid) · n_i positive, which is outward for closed, roughly star-shaped parts.
//
// Where the sensor's position is known (a single view, or each point's scanner station), no tree
// is needed: a sensor sees only surfaces that face it, so each normal is turned toward it, as
// PCL's and Open3D's camera orientation do. Only points seen nearly edge-on (their normal
// within about 10° of square to the line of sight, where the PCA sign toward the sensor is
// noise) take the sign on which their confidently turned neighbours agree.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

struct NormalEstimationParams {
  int neighbors = 12;  // k for the smallest PCA neighbourhood and for the orientation graph; 3..128.
  // Neighbourhood sizes tried per point, each twice the last (12, 24, 48, 96); 1..4. One gives
  // plain PCA of the k nearest. At σ = 0.1 % of the diagonal on a torus whose tube is 1 % of it,
  // four sizes turn 0.1 % of the normals the wrong way against 4.6 % with one.
  int scales = 4;
  // Where the sensors stood, when known: every normal is turned toward its own (above); empty:
  // unknown, oriented by propagation.
  std::vector<Vec3d> viewpoints;
  // Which of `viewpoints` saw each point (a scan index per point); empty: the first saw all.
  std::vector<uint32_t> station;
  // A sensor measures a point only along a free line of sight. Where more than this share of a
  // sample of the points is hidden from its sensor (something lies on the way, off the point's
  // own tangent plane), the positions are not where these points were seen from, and the
  // normals are oriented by propagation instead: PCL writes VIEWPOINT 0 0 0 when it knows no
  // sensor, and a cloud cut out of a map merged from a moving scanner's sweeps has no one
  // position (a car cut out of such a sweep: 37 % hidden from the origin its file names; the
  // views of a simulated depth camera, stereo steps and a room included, and merged scanner
  // stations: at most 4.8 %). Hidden points are not all turned wrong (a table behind a ball
  // still faces the camera), so the limit is high: two views of a ball on a table merged under
  // the first camera's position hide 12 %, and that position turns fewer normals wrong (2.8 %)
  // than propagation (6.2 %). 1 trusts the positions always.
  double max_hidden_share = 0.25;
};

absl::Status Validate(const NormalEstimationParams& params);

// What EstimateNormals decided about the sensors' positions.
struct NormalOrientation {
  double hidden_share = -1;  // Of the sample hidden from its sensor; -1: no positions given.
  bool toward_viewpoints = false;
};

// Unit normals, one per point; `orientation`, when given, says how they were turned. Errors:
// kInvalidArgument (fewer than 3 points, bad params), kCancelled. Cost: one k-NN query per
// point, one of the largest size where those k do not lie flat, an O(n k log(n k)) spanning tree,
// and O(n k) for the layers and each of the votes; with positions, rays from up to 4096 points
// toward their sensors through a grid of the occupied cells instead of the tree.
absl::StatusOr<std::vector<Vec3f>> EstimateNormals(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                                   JobContext& ctx, NormalOrientation* orientation = nullptr);

}  // namespace lsqsurf::core
