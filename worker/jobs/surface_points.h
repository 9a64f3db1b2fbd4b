// worker/jobs/surface_points.h — how every surface method takes its cloud's points
// (PointParams): the parameter table they all include, and the attributes carried to the mesh.
#pragma once

#include <cstdint>
#include <span>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/core/normals.h"
#include "worker/core/params.h"
#include "worker/jobs/job.h"
#include "worker/jobs/surface_params.h"

namespace lsqsurf::jobs {

// estimate_normals, normal_neighbors, viewpoint and point_attributes.
const core::ParamTable<PointParams>& PointParamsTable();

// The sensors `points.viewpoint` gives, into `normals`: one position for every point, or several
// with the cloud's per-point attribute "scan" naming each point's. Errors: kInvalidArgument (no
// scan attribute, a scan index that is not one of the positions').
absl::Status ChooseViewpoints(const PointParams& points, const core::PointCloud& cloud,
                              core::NormalEstimationParams& normals);

// What every surface method does to its cloud first: exact repeats dropped (statistic
// duplicate_points), isolated points removed where `points.remove_outliers` asks
// (outliers_removed), depth steps undone where `points.undo_depth_steps` asks and they are found
// (core::UndoDepthSteps per sensor; depth_step, depth_steps_moved, viewpoint_inferred), and normals estimated where the
// cloud has none, toward the sensors where known and where they see the points (normals_toward_viewpoint, 0 when the
// positions given hide too many points: viewpoint_hidden_share; normals_seconds), with progress on `ctx` from 0 to the
// share it returns (kNormalsShare when it estimates normals, else 0). Errors: kInvalidArgument (too few distinct
// points, no normals and estimate_normals false, bad viewpoints), kCancelled.
inline constexpr double kNormalsShare = 0.2;
absl::StatusOr<double> PrepareSurfaceCloud(const PointParams& points, core::PointCloud& cloud, core::JobContext& ctx,
                                           Statistics& statistics);

// The cloud's per-point attributes `points` names (by default colour and intensity, those it
// has) onto `mesh`'s vertices, with the statistics carried_attributes and carry_seconds.
// Errors: kInvalidArgument naming an attribute the cloud lacks, kCancelled.
absl::Status CarryPointAttributes(const PointParams& points, const core::PointCloud& cloud, core::JobContext& ctx,
                                  core::TriangleMesh& mesh, Statistics& statistics);

// Removes the components whose area is mostly (over kInventedShellShare) unmeasured by
// `unmeasured` (per vertex, 1 = unmeasured; a face is where most of its vertices are) and that
// either lie inside a larger one (its winding number at least ½ at most of kShellProbes faces
// spread over the component) or cross it (inside at one of them at least) with their measured
// part on its surface. A sensor sees no surface that another encloses, and
// no two real objects overlap, so such a shell is the method's own: PU on four depth views of
// a cow closed two of 0.5 % of the area each at its belly, 77-79 % unmeasured, one inside and
// one blistering through the skin it was fitted beside. A measured inner shell (a hollow part's
// sampled inner wall) and an object beside stay. Returns the shells removed.
inline constexpr double kInventedShellShare = 0.5;
inline constexpr size_t kShellProbes = 15;
inline constexpr double kShellOnSurfaceEdges = 3;
int64_t RemoveInventedInnerShells(core::TriangleMesh& mesh, std::span<const float> unmeasured);

// Where `points.fill_holes` asks: the holes of `mesh` closed (extract::FillHoles) and the
// vertex attribute kFilledAttribute added, with the statistics holes_filled, holes_left,
// filled_vertices, inner_shells_removed (RemoveInventedInnerShells) and fill_seconds. Errors: kCancelled.
absl::Status CloseHolesOnRequest(const PointParams& points, const core::PointCloud& cloud, core::JobContext& ctx,
                                 core::TriangleMesh& mesh, Statistics& statistics);

// The vertex attribute of a closed surface: 1 where a vertex lies farther than
// core::kUnmeasuredSpacings local spacings from every point of the cloud (the surface there was not
// measured: a filled hole, or the method's own extrapolation), 0 elsewhere; local spacings as
// core::LocalSpacing measures them.
inline constexpr char kFilledAttribute[] = "filled";
core::ScalarAttribute UnmeasuredVertices(const core::PointCloud& cloud, const core::TriangleMesh& mesh,
                                         core::JobContext& ctx);

}  // namespace lsqsurf::jobs
