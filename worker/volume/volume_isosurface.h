// worker/volume/volume_isosurface.h — isosurfaces of a reconstructed volume field.
//
// {Q_f = iso} is extracted on the adaptive J1a tetrahedra (extract/j1a_isosurface.h), starting
// from the vertices whose data says the level passes within about one spacing of them, with
// vertex normals from Q_∇f (pointing towards larger values). Surface is placed only inside the
// data's domain (inside the cells, or where a point set's kernels reach), so a level set that is
// closed inside the domain comes out closed and one that leaves it is cut at its boundary.
#pragma once

#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/volume/volume_field.h"

namespace lsqsurf::volume {

struct VolumeIsosurfaceParams {
  std::vector<double> iso_values;  // One surface per value; at least one.
  int field = 0;                   // Index into the field's names.
  int color_field = -1;            // −1: none; else Q of this field becomes a vertex attribute named like it.
  double resolution = 0.5;         // Finest J1a cube edge as a share of the median vertex spacing, 0.05..2.
  int64_t max_leaves = 20'000'000;
};

// Several iso-values are merged into one mesh with the vertex attribute "iso" (the value).
// Errors: kInvalidArgument (no iso-values, a level no vertex comes near: the message gives the
// field's range), kResourceExhausted, kCancelled.
absl::StatusOr<core::TriangleMesh> ExtractVolumeIsosurface(const VolumeField& field,
                                                           const VolumeIsosurfaceParams& params, core::JobContext& ctx);

}  // namespace lsqsurf::volume
