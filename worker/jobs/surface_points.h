// worker/jobs/surface_points.h — how every surface method takes its cloud's points
// (PointParams): the parameter table they all include, and the attributes carried to the mesh.
#pragma once

#include <cstdint>
#include <span>

#include "absl/status/status.h"
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

// The cloud's per-point attributes `points` names (by default colour and intensity, those it
// has) onto `mesh`'s vertices, with the statistics carried_attributes and carry_seconds.
// Errors: kInvalidArgument naming an attribute the cloud lacks, kCancelled.
absl::Status CarryPointAttributes(const PointParams& points, const core::PointCloud& cloud, core::JobContext& ctx,
                                  core::TriangleMesh& mesh, Statistics& statistics);

// Removes the components that lie inside another (winding number of the larger ones around them
// at least ½) and whose area is mostly (over kInventedShellShare) unmeasured by `unmeasured`
// (per vertex, 1 = unmeasured; a face is where most of its vertices are). A sensor sees no
// surface that another encloses, so such a shell is the method's own: PU on four depth views of
// a cow closed two, of 0.5 % of the area each and 79 % unmeasured, inside its belly. A measured
// inner shell (a hollow part's sampled inner wall) stays. Returns the shells removed.
inline constexpr double kInventedShellShare = 0.5;
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
