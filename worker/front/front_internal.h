// worker/front/front_internal.h — what the parts of front tracking share: grid nodes and
// crossings, the RAMLS surface of a front, markers, and the flow's Jacobian. front_tracking.cc
// holds the parameters and the time loop; gridlines.cc sampling on grid lines and volumes;
// markers.cc the marker mode; velocity_fields.cc the fields and their derivatives. Included by
// worker/front only.
#pragma once

#include <Eigen/Core>
#include <atomic>
#include <cmath>
#include <memory>
#include <span>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/extract/j1a.h"
#include "worker/front/front_tracking.h"
#include "worker/mls/algebraic_mls.h"

namespace lsqsurf::front {

using core::Vec3d;
using core::Vec3f;

using NodeKey = uint64_t;
inline NodeKey Key(uint32_t i, uint32_t j, uint32_t k) { return extract::PackVertex(i, j, k); }

struct Crossing {
  Vec3f point, normal;
};

struct ZCrossing {
  uint64_t column;  // i | j << 32.
  double z;
  bool entering;  // F goes from + (outside) to − (inside) along +z.
};

struct GridlineResult {
  std::vector<Crossing> crossings;     // In node order; x, y, z edges of each node.
  std::vector<ZCrossing> z_crossings;  // Sorted by column, then z.
};

// Samples F at `nodes` (sorted) of the grid of spacing h and finds the root on every x, y and
// z edge (or z only) between two defined nodes of opposite sign.
absl::StatusOr<GridlineResult> SampleGridlines(const core::ImplicitFunction& field, std::span<const NodeKey> nodes,
                                               double h, bool z_only, core::JobContext& ctx);

double VolumeOf(std::span<const ZCrossing> z, double h);

// The grid nodes within kNodeReach cells of any point, sorted. `marks` is a reusable dense
// bitmap of the (n+1)³ nodes (one bit each: 17 MB at h = 1/512, 135 MB on the h/2 grid of the
// shape error), left cleared.
std::vector<NodeKey> NodesNear(std::span<const Vec3f> points, double h, std::vector<bool>& marks);

// Points bucketed in cubes of edge `cell`, for the question "does a point facing the same way
// lie within d ≤ cell of here?" (the two sides of a sheet thinner than d do not count).
class SpacingGrid {
 public:
  explicit SpacingGrid(double cell) : cell_(cell) {}
  bool HasNear(const Vec3f& p, const Vec3f& normal, double distance) const {
    const double d2 = distance * distance;
    for (int d = 0; d < 27; ++d) {
      const auto it = buckets_.find(Bucket(p, d % 3 - 1, (d / 3) % 3 - 1, d / 9 - 1));
      if (it == buckets_.end()) continue;
      for (uint32_t k : it->second) {
        if (normals_[k].dot(normal) >= 0 && (points_[k] - p).squaredNorm() < d2) return true;
      }
    }
    return false;
  }
  void Add(const Vec3f& p, const Vec3f& normal) {
    buckets_[Bucket(p, 0, 0, 0)].push_back(static_cast<uint32_t>(points_.size()));
    points_.push_back(p);
    normals_.push_back(normal);
  }

 private:
  uint64_t Bucket(const Vec3f& p, int dx, int dy, int dz) const {
    auto c = [&](int a, int d) {
      return static_cast<uint64_t>(static_cast<int64_t>(std::floor(p[a] / cell_)) + d + (1 << 20));
    };
    return c(0, dx) | (c(1, dy) << 21) | (c(2, dz) << 42);
  }
  double cell_;
  absl::flat_hash_map<uint64_t, std::vector<uint32_t>> buckets_;
  std::vector<Vec3f> points_, normals_;
};

// Greedy thinning in the given order: a point is kept unless a kept point facing the same way
// lies within h/2 (the two sides of a sheet thinner than h/2 both stay).
Front Thin(const std::vector<Crossing>& crossings, double h);

absl::StatusOr<std::unique_ptr<mls::AlgebraicMlsFunction>> FrontFunction(const Front& front, double h,
                                                                         double support_factor, core::JobContext& ctx);

// F where the front's points face two opposite ways within the support: the smooth union of the
// two sides' fits where the far side lies in front of the near one (a gap closes), their smooth
// intersection where it lies behind (a neck or sheet pinches), with blend radius k. Both
// blends reduce to the nearer side's value (the plain side rule) where the two values differ by
// k or more, and close a gap or cut a neck narrower than k/2.
class TopologyField final : public core::ImplicitFunction {
 public:
  TopologyField(std::unique_ptr<mls::AlgebraicMlsFunction> sides, double blend)
      : sides_(std::move(sides)), blend_(blend) {}
  core::FieldValue Value(const Vec3d& x) const override {
    const core::FieldGradient g = ValueAndGradient(x);
    return {g.value, g.defined};
  }
  core::FieldGradient ValueAndGradient(const Vec3d& x) const override { return Blend(sides_->Sides(x)); }
  // Whether the blend changes F at x from the nearer side's value.
  bool BlendActsAt(const Vec3d& x) const {
    bool acts = false;
    Blend(sides_->Sides(x), &acts);
    return acts;
  }

 private:
  // The blended value from the two fits; also whether the blend changes the near side's value.
  core::FieldGradient Blend(const mls::SidesAt& s, bool* acts = nullptr) const {
    if (acts) *acts = false;
    if (!s.near.defined || !s.far.defined) return s.near;
    // Smooth minimum of a and b (a union); the intersection is −smin(−a, −b). With
    // m = clamp(½ + ½(b − a)/k): smin = b + (a − b)m − k m(1 − m), and its gradient is exactly
    // ∇b + (∇a − ∇b)m (the terms in ∇m cancel).
    const double sign = s.far_in_front ? 1 : -1;
    const double a = sign * s.near.value, b = sign * s.far.value;
    const double m = std::clamp(0.5 + 0.5 * (b - a) / blend_, 0.0, 1.0);
    core::FieldGradient out = s.near;
    out.value = sign * (b + (a - b) * m - blend_ * m * (1 - m));
    out.gradient = s.far.gradient + (s.near.gradient - s.far.gradient) * m;
    if (acts) *acts = m < 1;
    return out;
  }

  std::unique_ptr<mls::AlgebraicMlsFunction> sides_;
  double blend_;
};

// The function whose zero set is the front: the side rule's RAMLS function, blended where two
// sides meet when merge_distance > 0.
absl::StatusOr<std::unique_ptr<core::ImplicitFunction>> SurfaceFunction(const Front& front, double h,
                                                                        double support_factor, double merge_distance,
                                                                        core::JobContext& ctx);

// The z-gridline crossings, on a grid of spacing `grid`, of the RAMLS function (spacing h) of
// the front: what the volume and the shape error are measured from.
absl::StatusOr<std::vector<ZCrossing>> ZCrossings(const Front& front, double h, double grid, double support_factor,
                                                  double merge_distance, std::vector<bool>& marks,
                                                  core::JobContext& ctx);

absl::Status ValidateSpacing(double h);

// Marker points carry the step they were made at; older markers have been moved by the exact
// flow for longer and outrank younger ones when two crowd each other.
struct Markers {
  Front front;
  std::vector<int> birth;
};

// Drops every marker that an older (or, at equal age, earlier) kept marker facing the same way
// lies within `min_distance` of.
void ThinMarkers(Markers& m, double min_distance);

// Where the flow has stretched the markers apart, adds new ones. The midpoint of two markers
// facing the same way (within 60°) and at most 2h apart, with no marker facing that way within
// `gap` of it, is projected onto the RAMLS surface fitted to that side alone (the markers facing
// within 90° of the pair), so the two faces of a sheet never mix however thin it is. Midpoints
// only interpolate: a spot beyond the last marker, at a sheet's rim, is never made up. A
// projection that does not settle on the surface within h/2 is dropped.
absl::Status FillGaps(Markers& m, int step, double h, double gap, double support_factor, core::JobContext& ctx);

// The markers mode's topology changes: the markers where the blend of TopologyField changes F
// (two sides within the blend radius of each other, or one front inside another) go, and the
// gridline roots of the blended F around them, thinned against the markers that stay, take
// their place.
absl::Status ReplaceMergingMarkers(Markers& m, int step, double h, double support_factor, double merge_distance,
                                   std::vector<bool>& marks, core::JobContext& ctx);

// The largest eigenvalue of the symmetric part of ∇v: the fastest rate at which the flow pulls
// two nearby points apart (d|δ|/dt ≤ λ|δ|).
double LargestStrainRate(const Eigen::Matrix3d& jacobian);

void RaiseTo(std::atomic<double>& most, double value);

// Flow Jacobian ∇v by central differences (the fields are smooth; the step only has to be far
// below their length scale and far above rounding).
Eigen::Matrix3d Jacobian(const VelocityField& v, const Vec3d& x, double t);

}  // namespace lsqsurf::front
