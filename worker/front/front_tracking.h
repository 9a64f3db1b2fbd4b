// worker/front/front_tracking.h — meshless front tracking with RAMLS surfaces (seed §3;
// METHODS.md §2).
//
// The interface is a set of oriented points. Every step:
//  1. each point moves with classical RK4 along the velocity field; its normal is carried by the
//     flow's Jacobian (n ← n − Δt ∇vᵀ n, renormalized; the seed keeps the old normal, which then
//     lags the surface by the rotation of one step);
//  2. the points are re-sampled through the RAMLS function of the moved points (support 3h), in
//     one of two ways (Resampling):
//     * markers (the default): the moved points stay. Of two facing the same way closer than
//       h/2, the younger goes; the midpoint of two that the flow has pulled apart is projected
//       onto the RAMLS surface of their side and becomes a new point. Only new points carry a
//       fitting error, and a sheet's two faces are never fitted together.
//     * gridlines (the seed's): the function is sampled at the background-grid nodes near the
//       points (spacing h); every grid edge whose ends have opposite signs gives a new point (the
//       root on the edge, by regula falsi, with the fitted sphere's normal); new points
//       closer than h/2 to an already kept one are dropped. The whole front is replaced.
// The enclosed volume comes from the z-edges: along each z gridline the crossings alternate
// between entering (F goes from + to −) and leaving, and V = h² Σ (z_leave − z_enter).
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"

namespace lsqsurf::front {

// v(x, t). Implementations must be safe to call from many threads.
class VelocityField {
 public:
  virtual ~VelocityField() = default;
  virtual core::Vec3d At(const core::Vec3d& x, double t) const = 0;
};

// Zalesak's rigid rotation about the axis through (0.5, 0.5) parallel to z,
// v = (π/314)(0.5 − y, x − 0.5, 0): one revolution every 628 time units.
std::unique_ptr<VelocityField> ZalesakRotation();
// How LeVeque's deformation field changes in time; with either the shape returns at t = T.
enum class TimeModulation {
  kCosine = 0,    // cos(πt/T): Enright et al.'s smooth form. (Values are stored with track jobs.)
  kReversal = 1,  // +1 before T/2 and −1 after (0 at T/2 itself, so that an RK4 step centred there
                  // cancels its two halves as the exact flow does): the field "reversed at T/2" the
                  // seed describes; it stretches the shape more than the cosine (the flow runs at full
                  // speed until T/2).
};
// LeVeque's 3D deformation field, modulated in time as `modulation` says.
std::unique_ptr<VelocityField> EnrightDeformation(double period, TimeModulation modulation = TimeModulation::kCosine);
// A user field on a regular grid, interpolated trilinearly in space and constant in time.
// Node (i, j, k) lies at origin + (i, j, k) ⊙ spacing; `values` holds nx·ny·nz vectors, x
// fastest. Errors: kInvalidArgument (sizes, non-finite values, a spacing ≤ 0). Outside the grid
// the nearest boundary value is used.
absl::StatusOr<std::unique_ptr<VelocityField>> GridVelocity(core::Vec3d origin, core::Vec3d spacing, int nx, int ny,
                                                            int nz, std::vector<core::Vec3d> values);

// One classical RK4 step of dx/dt = v(x, t) from (x, t) to t + dt (dt may be negative: the flow
// run backwards).
core::Vec3d Rk4Step(const VelocityField& v, const core::Vec3d& x, double t, double dt);

// The analytic interfaces of the benchmarks (BENCHMARKS.md), inside = F < 0.
enum class InitialShape {
  kSphere,         // Radius 0.15 at (0.35, 0.35, 0.35): Enright's deformation test.
  kZalesakSphere,  // Radius 0.15 at (0.5, 0.75, 0.5), slot 0.05 wide cut from y = 0.6 to 0.725.
};

// The exact shape as a signed, distance-like value, < 0 inside: the signed distance for the
// sphere; for the slotted sphere the larger of the sphere's and the slot's (exact except near
// the slot's edges, where its magnitude is smaller).
double ShapeValue(InitialShape shape, const core::Vec3d& x);

struct Front {
  std::vector<core::Vec3f> points;
  std::vector<core::Vec3f> normals;  // Unit, outward.
};

// What keeps the front's points spread over the surface after each advection step.
enum class Resampling {
  // The seed's: the front is replaced by the roots of its RAMLS function on the gridlines of
  // spacing h, thinned to h/2, whenever the flow may have stretched it by regeneration_stretch
  // (every step with 1). Each replacement projects once more, and sheets thinner than about 2h
  // are lost (worker/front/README.md).
  kGridlines,
  // The advected points stay (markers): where they crowd, the younger of two facing the same way
  // within marker_spacing·h goes; where the flow stretches them apart, a new marker is projected
  // onto the RAMLS surface of that side alone. Only the new markers carry a fitting error.
  kMarkers,
};

struct TrackingParams {
  double h = 1.0 / 128;           // Background grid spacing in the unit cube [0, 1]³, 1/512..1/8.
  double dt = 1.0;                // Time step, > 0.
  int steps = 1;                  // Number of steps, 1..100000.
  int output_stride = 1;          // Report every this many steps (and the last), ≥ 1.
  double support_factor = 3.0;    // RAMLS support radius in units of h (the seed's 3).
  size_t max_points = 4'000'000;  // A front that grows past this stops with kResourceExhausted.
  Resampling resampling = Resampling::kMarkers;
  double marker_spacing = 0.5;  // kMarkers: the closest two markers facing the same way may come, units of h, 0.1..1.
  double marker_gap = 0.75;     // kMarkers: the midpoint of two markers with no marker within this gets one,
                                // units of h, (marker_spacing, 1].
  // Topology changes, units of h, 0..support_factor/2; 0 (the default) keeps every sheet and gap
  // however thin. Two fronts (or two parts of one) that come closer than this merge, and a neck
  // or sheet thinner than it pinches off: where a point's neighbourhood holds two opposite-facing
  // sides, F is their smooth union (a gap) or smooth intersection (a neck) of blend radius
  // 2·merge_distance·h instead of the nearer side's fit. In the markers mode the markers where
  // that blend acts are replaced by the gridline roots of the blended F. 1.25–1.5 with the
  // default support: below that the markers mode lets a neck thin into a thread the RAMLS fits
  // cannot describe before it pinches.
  double merge_distance = 0;
  // kGridlines: the front is re-generated once the flow may have spread two neighbouring points
  // apart by this factor since the last re-generation, 1..4. The bound is exp(∫ λ dt), λ the
  // largest strain rate (eigenvalue of the symmetric part of ∇v) at any point; steps in between
  // only advect. 1 re-generates every step, the seed's literal scheme: each re-generation adds a
  // fitting error, and where the seed's field is reversed at T/2 the returning flow amplifies the
  // errors added at the peak stretch until the front grows without bound (README). Rigid motions
  // (Zalesak) never stretch, so they are never re-generated after the start. With merge_distance
  // > 0 every step re-generates: topology changes happen at re-generations.
  double regeneration_stretch = 1.5;
};

// The one description of every TrackingParams field (output_stride is called "stride");
// Validate() checks it, with the rules that 1/h is whole and marker_gap > marker_spacing.
const core::ParamTable<TrackingParams>& TrackingParamTable();
absl::Status Validate(const TrackingParams& params);

struct FrameStats {
  int step = 0;
  double time = 0;
  size_t points = 0;
  double volume = 0;         // Enclosed volume from the z gridlines.
  double volume_change = 0;  // (V − V₀) / V₀.
  double seconds = 0;        // Wall time of the steps since the previous frame.
};

// Samples the exact shape on the gridlines of spacing `h` (the same rule as every step).
// Errors: kInvalidArgument (h out of range).
absl::StatusOr<Front> SampleInitialFront(InitialShape shape, double h);

// Samples any closed surface, given as an implicit function (< 0 inside, about a signed distance
// near its zero set, defined in the box), on the gridlines of spacing `h` in the box [lo, hi]
// (clipped to the unit cube): the rule of SampleInitialFront. Errors: kInvalidArgument (h, an
// empty box), kFailedPrecondition (no surface crossed).
absl::StatusOr<Front> SampleFront(const core::ImplicitFunction& shape, const core::Vec3d& lo, const core::Vec3d& hi,
                                  double h);

// The three measures below use the surface Track uses: the RAMLS function of the front (support
// `support_factor`·h), blended where two sides meet when `merge_distance` > 0.

// Volume of the region where the front's RAMLS function is negative, from the z gridlines of
// spacing `h` (the measure used for every frame). Errors: kInvalidArgument.
absl::StatusOr<double> FrontVolume(const Front& front, double h, double support_factor = 3.0,
                                   double merge_distance = 0);

// The front's surface as a triangle mesh: the RAMLS function (support `support_factor`·h)
// extracted by marching tetrahedra on cubes of edge h around the points, with vertex normals.
// Its enclosed volume cross-checks FrontVolume. Errors: kInvalidArgument, kResourceExhausted,
// kCancelled.
absl::StatusOr<core::TriangleMesh> FrontMesh(const Front& front, double h, core::JobContext& ctx,
                                             double support_factor = 3.0, double merge_distance = 0);

// E1 = ∫ |χ_front − χ_exact| dV (BENCHMARKS.md), with χ_front from the crossings of the front's
// RAMLS function on z gridlines of spacing `h` / 2 (exact along each line, sampled across).
absl::StatusOr<double> ShapeError(const Front& front, InitialShape exact, double h, double support_factor = 3.0,
                                  double merge_distance = 0);

// Advects `initial` for params.steps steps. `on_frame(stats, front)` is called for step 0 and
// then every output_stride steps and after the last; returning a non-OK status stops tracking
// with that status. Errors: kInvalidArgument (bad parameters, an empty front, non-finite
// velocities), kFailedPrecondition (the front vanished), kResourceExhausted (more than
// max_points points), kCancelled.
absl::Status Track(const Front& initial, const VelocityField& velocity, const TrackingParams& params,
                   core::JobContext& ctx, const std::function<absl::Status(const FrameStats&, const Front&)>& on_frame);

}  // namespace lsqsurf::front
