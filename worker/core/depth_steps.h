// worker/core/depth_steps.h — the depth steps of a single view undone.
//
// A stereo rig measures disparity in whole (or sixteenth) pixels and a structured-light depth
// camera does the same, so its depth takes only the values z = 1 / (k Δ): every surface comes
// back as terraces of exactly constant depth, square to the optical axis, each many point spacings
// wide where the surface is steep in depth (a floor seen from eye height). On such a cloud every
// small neighbourhood is exactly flat, so normals are the optical axis everywhere, the noise
// estimate is zero, and a surface through the points has a cliff at each riser (a single-view
// room came back from PU in 297 components, 28 % of it facing away from the camera).
//
// Such a cloud is found by its signature, measured on a sample of 48-neighbourhoods: many of
// them exactly flat, nearly all of those square to one direction (or, for a time-of-flight
// camera's range steps, to the line of sight), their depths on several levels. A smooth view,
// a sampled mesh and a CAD part (flat faces in many directions, or a plate's two levels) are not.
// Where it is found, each point is moved along its own ray onto a plane fitted to its neighbours
// in the image (the points nearest in direction from the sensor, as a pixel window would give,
// those within a few steps of its own depth, so that depth edges stay), never by more than half
// a step: the true depth lies within half a step of the quantized one. In perspective a plane's
// inverse depth is linear in the image coordinates, so the fit is linear in 1 / depth.
#pragma once

#include <cstddef>
#include <optional>
#include <span>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

struct DepthStepParams {
  int sample = 1024;          // Points whose neighbourhoods test for the signature.
  int neighbors = 48;         // Size of those neighbourhoods.
  double exact_share = 0.2;   // Of the sample exactly flat, at least (a smooth view: 0; a room in steps: 55 %).
  double family_share = 0.9;  // Of those square to one direction or to the line of sight, at least
                              // (the stepped room: 100 %; fandisk, 43 % exact: 56 %).
  int levels = 8;             // Depth levels holding points, at least (a plate seen square: 2).
  int window = 121;           // Neighbours in the image of each plane fit (an 11 × 11 pixel window),
  int widest_window = 1936;   // four times as many, up to this (44 × 44), where they hold one level only.
  double window_steps = 3.5;  // Only neighbours within this many steps of the point's depth enter its fit.
};

// What UndoDepthSteps found and did.
struct DepthStepResult {
  bool found = false;
  double exact_share = 0;     // Of the sample.
  double family_share = 0;    // Of the exact part of the sample.
  bool radial = false;        // Steps in range (square to the line of sight), not in depth along one axis.
  size_t levels = 0;          // Depth levels holding points.
  double step = 0;            // At the median depth, in model units.
  double step_agreement = 0;  // Share of the gaps between levels that whole multiples of the step explain.
  size_t moved = 0;           // Points moved.
  bool eye_inferred = false;  // No position was given, and the steps place the sensor at the origin.
};

// Finds the depth steps of the cloud `points` seen from `eye` and, where found, moves the points
// off them (above). Without `eye`, the cloud is taken to lie in its sensor's frame, as a depth
// camera's or a stereo rig's own export does, where disparity steps measured from the origin
// say so (they fit a sensor there, and one 30 % of the depth nearer or farther far worse). Errors: kInvalidArgument
// (bad params), kCancelled. Cost: one 48-neighbour query per sampled point, a sort of the depths and, where steps are
// found, a k-d tree over the points' image positions and one `window`-neighbour query and 3 × 3 solve per point.
absl::StatusOr<DepthStepResult> UndoDepthSteps(std::span<Vec3f> points, const std::optional<Vec3d>& eye,
                                               const DepthStepParams& params, JobContext& ctx);

}  // namespace lsqsurf::core
