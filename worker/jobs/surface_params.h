// worker/jobs/surface_params.h — the parts of a surface job's parameters that its input and the
// shared extractor read too (below surface_job.h, which includes this).
#pragma once

#include <string>
#include <vector>

#include "worker/core/normals.h"

namespace lsqsurf::jobs {

// How a surface job takes its cloud's points: normals for clouds that come without them, where
// the sensor stood, and which per-point attributes its mesh keeps.
struct PointParams {
  bool estimate_normals = true;  // PCA + spanning-tree orientation; false rejects clouds without normals.
  int normal_neighbors = core::NormalEstimationParams{}.neighbors;  // Smallest k of the PCA, 3..128.
  // Where the sensor stood (x, y, z in the cloud's units), or empty when unknown: estimated
  // normals are turned toward it (core::NormalEstimationParams::viewpoint). The client fills it
  // from a file that says (a PCD's VIEWPOINT).
  std::vector<double> viewpoint;
  // Per-point attributes carried to the mesh's vertices (core::CarryAttributes), by name,
  // separated by commas; empty = colour (red, green, blue) and intensity, those the cloud has;
  // "none" = none.
  std::string point_attributes;
  // Isolated points (flying pixels, dust, stray returns; core::RemoveIsolatedPoints) are
  // removed before anything else reads the cloud.
  bool remove_outliers = true;
  // Where one sensor position per scan is known and the points lie on quantized depth levels
  // (stereo disparity, depth-camera steps), each point is moved along its ray, by at most half a
  // step, onto a plane fitted across the steps around it (core::UndoDepthSteps).
  bool undo_depth_steps = true;
  // The holes the data leave closed (extract::FillHoles), each vertex farther than three
  // spacings from the data marked in the vertex attribute "filled"; false: the surface stays
  // open where nothing was measured.
  bool fill_holes = false;
};

// Where the shared extractor looks for the surface, for the methods without their own.
enum class SurfaceExtractor { kUniformGrid = 0, kJ1a = 1 };

}  // namespace lsqsurf::jobs
