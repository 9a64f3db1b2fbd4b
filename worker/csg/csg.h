// worker/csg/csg.h — Boolean combinations of implicit solids, extracted as one closed mesh.
//
// Every operand is an implicit function, negative inside: the analytic primitives are exact
// signed distances, a job reference is a kept PU function (seed §2). Union is the minimum,
// intersection the maximum, difference max(a, −b): the classic R-function-free CSG of implicit
// solids, whose zero set is the boundary of the combined solid, with creases where operands
// meet. The gradient is the active operand's, so the extractor's crease splitting
// (extract/creases.h) puts the mesh's edges on the intersection curves.
//
// Extraction runs on J1a tetrahedra refined only where the combined surface passes: near each
// operand's own surface (its points for a PU function, a Lipschitz-bounded octree descent for a
// primitive), keeping the places where the combined function is near zero, so the work follows
// the result's area, not the operands'.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/csg/expression.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::csg {

// A solid that a `job:ID` stands for, negative inside; its callbacks own what they evaluate.
struct Operand {
  // F (own coordinates) with a trustworthy sign everywhere, `defined` where surface may be
  // placed (a fit's own value far from its data may have either sign). Required.
  std::function<core::FieldGradient(const core::Vec3d&, bool with_gradient)> value;
  core::Box3 bounds;                        // Holds the whole surface; outside it the solid is empty.
  std::vector<core::Vec3f> surface_points;  // Points on or next to its surface (the fitted cloud).
  double cell_size = 0;                     // The finest extraction leaf it was made with, model units.
  // Whether a point (own coordinates) lies at one of its creases, where extraction needs the
  // finest cells whatever the curvature; unset: everywhere.
  std::function<bool(const core::Vec3d&)> near_crease;
};

// Resolves a job id to its operand. Errors: whatever the caller reports (kNotFound,
// kFailedPrecondition, ...), passed on with the id.
using OperandResolver = std::function<absl::StatusOr<Operand>(const std::string& job_id)>;

struct CsgParams {
  // Edge of the finest extraction leaves in model units; 0 = the finest of the referenced
  // jobs' own, or 1/256 of the solid's longest side when none is referenced.
  double cell_size = 0;
  // Cells are split towards cell_size where flat triangles would stray farther than this share
  // of the solid's diagonal (as PuExtractParams::chord_error), and always along intersection
  // curves and a PU operand's creases.
  double chord_error = extract::kDefaultChordError;
  int64_t max_leaves = 20'000'000;
  // Edges are split on the intersection curves (and on the operands' own creases), then relaxed
  // tangentially: crisp curves and no slivers along them.
  extract::MarchingOptions marching{.crease_angle = 30, .relax_steps = 4};
};

absl::Status Validate(const CsgParams& params);

struct CsgStats {
  int64_t seeds = 0;  // Starting points kept near the combined surface.
  double cell_size = 0;
};

// F of an expression. Thread-safe to evaluate concurrently.
class CsgFunction final : public core::ImplicitFunction {
 public:
  ~CsgFunction() override;
  core::FieldValue Value(const core::Vec3d& x) const override;
  core::FieldGradient ValueAndGradient(const core::Vec3d& x) const override;
  core::FieldGradient ValueAndGradientOnly(const core::Vec3d& x) const override;

  // Index of the operand (primitive or job, in order of appearance) that decides F at x.
  int ActiveOperand(const core::Vec3d& x) const;
  int operand_count() const;
  const core::Box3& bounds() const;  // Of the solid; finite.

  // Defined in csg.cc: only BuildCsg makes one, so the constructor and accessor open nothing
  // to other modules.
  struct Impl;
  explicit CsgFunction(std::unique_ptr<Impl> impl);
  const Impl& impl() const { return *impl_; }

 private:
  std::unique_ptr<Impl> impl_;
};

// The largest solid, in model units across: past it cell sizes and extents lose their meaning in
// doubles (sphere(r=1e308) once made the extraction run without bound).
inline constexpr double kMaxSolidExtent = 1e12;

// Errors: kInvalidArgument (an unbounded solid, e.g. a lone plane, an empty intersection of
// bounds, or one wider than kMaxSolidExtent), and the resolver's errors.
absl::StatusOr<std::unique_ptr<CsgFunction>> BuildCsg(const CsgNode& root, const OperandResolver& resolve);

// About how many finest cells the extraction seeds along the surface (the work and memory of
// ExtractCsg grow with it): for each primitive its area within the solid's box over the cell's
// area, for each job its points. Checked against max_leaves before extraction, and at submission
// for solids without job references. Errors: kInvalidArgument (bad parameters).
absl::StatusOr<double> EstimateSurfaceCells(const CsgFunction& function, const CsgParams& params);
// kResourceExhausted, saying what to change, when that estimate is past max_leaves.
absl::Status CheckExtractionSize(const CsgFunction& function, const CsgParams& params);

// The boundary of the solid, with the per-vertex attribute "operand" (ActiveOperand).
// Errors: kInvalidArgument, kResourceExhausted (the estimate or the cells past max_leaves),
// kFailedPrecondition (an empty solid), kCancelled (checked throughout).
absl::StatusOr<extract::IsosurfaceResult> ExtractCsg(const CsgFunction& function, const CsgParams& params,
                                                     core::JobContext& ctx, CsgStats* stats = nullptr);

}  // namespace lsqsurf::csg
