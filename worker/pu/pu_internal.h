// worker/pu/pu_internal.h — what the parts of the PU engine share: the local fit, the fitting
// tree, the function's state, and the steps that building, editing and reading a function all use.
// Only files of worker/pu include it.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <span>
#include <string_view>
#include <vector>

#include "worker/core/binary.h"
#include "worker/core/kd_tree.h"
#include "worker/core/noise.h"
#include "worker/pu/orthogonal_fit.h"
#include "worker/pu/pu.h"
#include "worker/pu/sharp_fit.h"

namespace lsqsurf::pu {

using core::Vec3d;
using core::Vec3f;

constexpr double kSqrt3 = 1.7320508075688772;
// Cells holding more points are split without trying a fit: at any useful threshold a fit over
// thousands of points fails, and gathering them is the expensive part at coarse levels.
constexpr uint32_t kMaxPointsToFit = 1024;
// The fitting ball of a sparse cell grows to at most this multiple of its support radius.
constexpr double kMaxRadiusGrowth = 4.0;
// Share of support points whose normal may oppose the fitted gradient.
constexpr double kMaxInvertedShare = 0.1;
// The local spacing of a point, for the coverage test: the distance to its 8th neighbour (about
// two sample spacings on a surface, robust to pairs of nearly coincident points).
constexpr size_t kSpacingNeighbors = 8;
// Beyond the rim of the data (the points near x lie to one side of it, as past a single view's
// silhouette) F is defined only within this share of `coverage_factor`'s reach: the full reach
// closes chance gaps where points surround x, but past a rim it would run a band of invented
// surface along every edge the sensor saw.
constexpr double kRimReachShare = 0.4;
// How many of x's nearest points the rim test reads, and the angular gap between them (seen
// about their mean normal) above which they lie to one side of x.
constexpr size_t kRimNeighbors = 20;
// The test reads points within this multiple of the reach (what tile margins and a remove
// edit's changed region must allow for).
constexpr double kRimReadFactor = 1.5;
constexpr double kRimGap = 3.14159265358979323846;
// The least length of their mean normal (in units of one normal) for the test to apply: where
// the normals turn more (about 25° from their mean on average), the data has no one tangent plane.
constexpr double kRimNormalAgreement = 0.8;
// Fits over larger balls (coarse cells) are made on an even subsample of this many points; the
// error test still runs over every point, so an accepted fit meets the bound on all of them.
// At worst a cell whose full fit would have passed is split.
constexpr size_t kMaxFitSamples = 256;
// Noisy data (σ above the error threshold): the error bound in units of σ, and the fewest points
// a fit may use (a fit over N points with T terms carries about σ√(T/N) of noise into F).
constexpr double kNoiseBoundFactor = 3.0;
constexpr int kNoisyMinPoints = 80;
// A quadric label in FitLabel::degree.
constexpr int kQuadricLabel = 5;

struct LocalFit {
  Vec3d centre = Vec3d::Zero();  // Of the leaf.
  double support_radius = 0;     // R_i of the PU weight.
  Vec3d origin = Vec3d::Zero();  // Local frame: weighted centroid, tangents, mean normal.
  Vec3d tangent_u = Vec3d::UnitX(), tangent_v = Vec3d::UnitY(), normal = Vec3d::UnitZ();
  double scale = 1;                              // The fitting radius (larger than the support in sparse leaves);
                                                 // tangent coordinates are divided by it.
  std::array<double, kMaxTerms> coefficients{};  // Height polynomial, or quadric in y = (x − origin)/scale.
  int8_t degree = 0;
  int8_t depth = 0;
  bool quadric = false;
  Feature feature = Feature::kSmooth;
  int32_t sharp = -1;  // Index of its SharpFit where the fit has sheets (feature != kSmooth).

  // f(x) and ∇f(x); f > 0 on the side the normals point to.
  double Evaluate(const Vec3d& x, Vec3d* gradient) const {
    const Vec3d d = x - origin;
    if (quadric) {
      const Vec3d y = d / scale;
      const auto& q = coefficients;
      const double value = q[0] + q[1] * y.x() + q[2] * y.y() + q[3] * y.z() + q[4] * y.x() * y.x() +
                           q[5] * y.y() * y.y() + q[6] * y.z() * y.z() + q[7] * y.x() * y.y() + q[8] * y.x() * y.z() +
                           q[9] * y.y() * y.z();
      if (gradient) {
        *gradient = Vec3d(q[1] + 2 * q[4] * y.x() + q[7] * y.y() + q[8] * y.z(),
                          q[2] + 2 * q[5] * y.y() + q[7] * y.x() + q[9] * y.z(),
                          q[3] + 2 * q[6] * y.z() + q[8] * y.x() + q[9] * y.y()) /
                    scale;
      }
      return value;
    }
    BivariatePolynomial p;
    p.coefficients = coefficients;
    p.degree = degree;
    double h, hu, hv;
    p.Evaluate(tangent_u.dot(d) / scale, tangent_v.dot(d) / scale, h, hu, hv);
    if (gradient) *gradient = normal - (hu * tangent_u + hv * tangent_v) / scale;
    return normal.dot(d) - h;
  }
};

struct Node {
  uint32_t x = 0, y = 0, z = 0;
  int level = 0;
  int32_t first_child = -1;  // Children are contiguous; child i has offsets (i&1, i>>1&1, i>>2&1).
  int32_t fit = -1;
};

inline double Theta(double s2) {
  const double t = 1 - s2;
  return t * t * t * t;
}

// The input points and what derives from them alone. An edit that keeps the points (set_degree,
// refit) shares them with the function it edits, so it rebuilds no point index.
struct PointData {
  std::vector<Vec3f> positions;
  std::vector<Vec3f> normals;        // Kept for refits of local edits.
  std::vector<float> local_spacing;  // Per point: distance to its kSpacingNeighbors-th neighbour.
  std::unique_ptr<core::KdTree> kd_tree;
};

struct PuFunction::Impl {
  PuStats stats;
  std::shared_ptr<PointData> cloud = std::make_shared<PointData>();  // Not changed once built.
  PuParams params;  // The effective parameters of the fits (after the noise adjustment).
  Vec3d origin = Vec3d::Zero();
  double root_edge = 1;
  int deepest_level = 0;
  std::vector<Node> nodes;
  std::vector<LocalFit> fits;
  std::vector<SharpFit> sharp_fits;
  // For every node (leaves only are filled): the fits whose support meets the node's cube.
  std::vector<uint32_t> influence_offsets;
  std::vector<uint32_t> influence;
  bool coverage_check = true;
  double coverage_factor = 1.25;
  double rim_reach_share = kRimReachShare;  // 1: no rim test (KeepFullReachPastRims).
  // The length ε0 and the chord error are shares of: the points' bounding-box diagonal, or, for a
  // tile's function, the whole cloud's (0 = the points' own).
  double frame_diagonal = 0;

  double Diagonal() const {
    return frame_diagonal > 0 ? frame_diagonal : core::Diagonal(core::BoundingBox(cloud->positions));
  }

  double Edge(int level) const { return std::ldexp(root_edge, -level); }
  Vec3d Centre(const Node& n) const { return origin + (Vec3d(n.x, n.y, n.z) + Vec3d::Constant(0.5)) * Edge(n.level); }

  int32_t LeafAt(const Vec3d& x) const {
    const Vec3d g = (x - origin) / root_edge;
    if (!(g.minCoeff() >= 0 && g.maxCoeff() <= 1)) return -1;
    int32_t index = 0;
    while (nodes[static_cast<size_t>(index)].first_child >= 0) {
      const Node& n = nodes[static_cast<size_t>(index)];
      const Vec3d c = Centre(n);
      const int octant = (x.x() >= c.x() ? 1 : 0) | (x.y() >= c.y() ? 2 : 0) | (x.z() >= c.z() ? 4 : 0);
      index = n.first_child + octant;
    }
    return index;
  }

  double EvaluateFit(const LocalFit& fit, const Vec3d& x, Vec3d* gradient) const {
    return fit.sharp >= 0 ? sharp_fits[static_cast<size_t>(fit.sharp)].Evaluate(x, gradient)
                          : fit.Evaluate(x, gradient);
  }

  // Calls visit(fit, s²) for every fit whose support holds x. Returns the fit whose support
  // comes closest when none holds it (nullptr when none is near at all).
  template <typename Visit>
  const LocalFit* ForEachSupport(const Vec3d& x, Visit&& visit) const {
    const int32_t leaf = LeafAt(x);
    if (leaf < 0) return nullptr;
    const LocalFit* closest = nullptr;
    double closest_s2 = std::numeric_limits<double>::infinity();
    for (uint32_t k = influence_offsets[static_cast<size_t>(leaf)];
         k < influence_offsets[static_cast<size_t>(leaf) + 1]; ++k) {
      const LocalFit& fit = fits[influence[k]];
      const double s2 = (x - fit.centre).squaredNorm() / (fit.support_radius * fit.support_radius);
      if (s2 < 1) visit(fit, s2);
      if (s2 < closest_s2) closest_s2 = s2, closest = &fit;
    }
    return closest;
  }

  core::FieldGradient Evaluate(const Vec3d& x, bool with_gradient, bool decide_defined = true) const {
    double sum_theta = 0, sum_value = 0;
    Vec3d sum_grad_theta = Vec3d::Zero(), sum_grad_value = Vec3d::Zero();
    const LocalFit* closest = ForEachSupport(x, [&](const LocalFit& fit, double s2) {
      const double theta = Theta(s2);
      Vec3d grad_f;
      const double f = EvaluateFit(fit, x, with_gradient ? &grad_f : nullptr);
      sum_theta += theta;
      sum_value += theta * f;
      if (with_gradient) {
        const double t = 1 - s2;
        const Vec3d grad_theta = (-8 * t * t * t / (fit.support_radius * fit.support_radius)) * (x - fit.centre);
        sum_grad_theta += grad_theta;
        sum_grad_value += grad_theta * f + theta * grad_f;
      }
    });
    core::FieldGradient out;
    if (!(sum_theta > 0)) {
      // Between supports (possible next to leaves without points): the closest fit gives the
      // sign, so that tetrahedra there still classify their corners; no surface is placed here.
      out.value = closest ? EvaluateFit(*closest, x, with_gradient ? &out.gradient : nullptr)
                          : std::numeric_limits<double>::quiet_NaN();
      return out;
    }
    out.value = sum_value / sum_theta;
    if (with_gradient)
      out.gradient = (sum_grad_value * sum_theta - sum_value * sum_grad_theta) / (sum_theta * sum_theta);
    out.defined = true;
    if (coverage_check && decide_defined) out.defined = Covered(x);
    return out;
  }

  // The evaluation-time coverage criterion (pu.h), with the tighter reach past the data's rim,
  // and the point nearest x it was judged by.
  struct Coverage {
    core::Neighbor nearest;
    bool covered = false;
  };
  Coverage CoverageAt(const Vec3d& x) const;
  bool Covered(const Vec3d& x) const { return CoverageAt(x).covered; }
  // Whether the points nearest x, within `radius`, lie to one side of it.
  bool BeyondRim(const Vec3d& x, double radius) const;
};

struct BuildContext {
  BuildContext(const PuParams& p, const PuFunction::Impl& m, std::span<const Vec3f> n, double bound)
      : params(p),
        impl(m),
        normals(n),
        error_bound(bound),
        cos_max_angle(std::cos(p.max_normal_angle * M_PI / 180.0)),
        sharp{std::cos(p.sharp_angle * M_PI / 180.0), SharpParams{}.corner_share} {}
  const PuParams& params;
  const PuFunction::Impl& impl;
  std::span<const Vec3f> normals;
  double error_bound;  // ε0 in model units.
  double cos_max_angle;
  SharpParams sharp;
  // Tiled builds (pu_tiles.h): no cell whose support radius exceeds `max_support` is fitted and
  // no fitting ball grows beyond it, so that every decision reads only points within
  // 2 × max_support of the region it serves;
  // neighbours are taken in a canonical order, so that sums do not depend on which points the
  // kd-tree holds besides; and with `region`, cells whose supports cannot reach it are not grown.
  double max_support = std::numeric_limits<double>::infinity();
  bool canonical_order = false;
  const core::Box3* region = nullptr;
};

struct CellOutcome {
  bool split = false;
  bool has_fit = false;
  bool unmet = false;
  LocalFit fit{};
  std::optional<SharpFit> sharp;           // With fit.feature != kSmooth.
  std::array<uint32_t, 9> child_ranges{};  // Boundaries of the children's point ranges.
};

struct Scratch {
  std::vector<core::Neighbor> neighbors;
  std::vector<double> u, v, w, weight;
  std::vector<double> sample_u, sample_v, sample_w, sample_weight;
  std::vector<char> in_support;
  std::vector<Vec3d> points, normals;
  OrthogonalFitter fitter;
};

// The twofold adaptive decision for one cell (pu_fit.cc): `inside` are the indices of the points
// in its cube, starting at `begin` of the whole order.
CellOutcome ProcessCell(const BuildContext& bc, const Node& node, std::span<uint32_t> inside, uint32_t begin,
                        Scratch& s);

// The fitting tree below the `current` leaves, level by level: every cell of a level is fitted in
// parallel, then split or kept (with its fit) in order, so the tree does not depend on the thread
// count. `ranges[node]` is the node's slice of `order` (the indices of the points in its cube);
// `stats` per-depth vectors must hold max_depth + 1 entries.
absl::Status GrowSubtrees(const BuildContext& bc, PuFunction::Impl& impl, std::vector<uint32_t>& order,
                          std::vector<std::array<uint32_t, 2>>& ranges, std::vector<int32_t> current, int max_depth,
                          PuStats& stats, core::JobContext& ctx);

// Leaf → fits whose support meets it, so that an evaluation visits one short list
// (pu_support_index.cc).
absl::Status IndexInfluence(PuFunction::Impl& impl, core::JobContext& ctx);

// IndexInfluence for an edit, without visiting every fit again. `after` is `before` with the
// fits of the `touched` leaves replaced by `new_fits` (indices in `after`; a touched leaf may
// have been split) and the fits renumbered by `renumber` (before's index → after's; empty when
// unchanged). An unchanged fit meets the same cubes as before, so only the leaves that a
// replaced or a new support meets, and the leaves new to the tree, get their lists rebuilt; the
// rest are renumbered. The result equals IndexInfluence(after) entry for entry.
absl::Status UpdateInfluence(const PuFunction::Impl& before, PuFunction::Impl& after, std::span<const int32_t> touched,
                             std::span<const int32_t> new_fits, std::span<const int32_t> renumber,
                             core::JobContext& ctx);

// The fitting tree's root cube for points in `box` (pu_fit.cc).
void RootCube(const core::Box3& box, Vec3d& origin, double& edge);

// Whether `p` lies in `box` with its upper sides left out, so that boxes tiling space own every
// point once.
inline bool InHalfOpenBox(const core::Box3& box, const Vec3d& p) {
  return (p.array() >= box.min().array()).all() && (p.array() < box.max().array()).all();
}

// The parameters the fits use on a cloud of scan noise `noise`: where σ exceeds error_threshold,
// the threshold becomes 3σ, min_points at least 80 and sharp fits are off (pu_fit.cc). Fills the
// noise, threshold and min_points of `stats`.
PuParams EffectiveParams(const PuParams& params, const core::NoiseEstimate& noise, double diagonal, PuStats& stats);

// A mesh with its attributes as bytes (pu_storage.cc), inside a kept surface or a tile's part.
// ReadMesh returns what is wrong ("" when nothing), face indices checked.
void WriteMesh(const core::TriangleMesh& mesh, core::BinaryWriter& w);
void WriteExtractParams(const PuExtractParams& p, core::BinaryWriter& w);
bool ReadExtractParams(core::BinaryReader& r, PuExtractParams& p);
std::string_view ReadMesh(core::BinaryReader& r, core::TriangleMesh& mesh);

// How far beyond a box the extraction tree must be built for its leaves inside the box to be the
// whole tree's: four cells of the coarsest level Extract keeps around the data (pu_extract.cc).
double ExtractionReach(double root_edge, double mean_spacing, const PuExtractParams& params);

// One tile's part of Extract: the faces whose J1a leaf has its centre in `core` (half-open),
// marched on a tree built over `core` and its ExtractionReach with Extract's finer leaves at
// corners, acute creases and thin walls (not its topology fallback, a decision over the whole
// surface), so that they are the whole surface's faces there; then creases and relaxation with
// the tile's border vertices (`seam`) fixed, so that neighbouring tiles meet on the same vertices
// (named by trace.vertex_edges). `function` must be exact over `core` grown by ExtractionReach
// (BuildPuInFrame with that region).
struct TileSurface {
  extract::IsosurfaceResult surface;  // Traced.
  std::vector<char> seam;             // Per vertex.
};
absl::StatusOr<TileSurface> ExtractTile(const PuFunction& function, const PuExtractParams& params,
                                        const core::Box3& core, core::JobContext& ctx);

}  // namespace lsqsurf::pu
