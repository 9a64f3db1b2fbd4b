#include "worker/front/front_tracking.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>

#include "absl/container/flat_hash_map.h"
#include "worker/core/implicit_function.h"
#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/extract/j1a.h"
#include "worker/mls/algebraic_mls.h"

namespace lsqsurf::front {
namespace {

using core::Vec3d;
using core::Vec3f;

constexpr double kRadius = 0.15;
// Root refinement on a grid edge: regula-falsi steps (core::RefineRootOnSegment; superlinear, 8
// bring the bracket far below 1e-6 h on smooth fronts).
constexpr int kRootSteps = 8;
// A bracketed root whose |F| / |∇F| stays above this share of h is not a root but a jump of F:
// the side rule switches fits where the nearest point changes sides, and on an open rim or a
// fold the two fits can disagree in sign there. Such a "root" lies between the two sides, off
// both; kept, it seeds a sheet that the next steps multiply (Enright's test, reversed at T/2,
// h = 1/128: the front exploded from t ≈ 1.05, and without these roots it holds to t ≈ 1.6).
constexpr double kRootResidual = 0.01;
// The grid nodes sampled around each point: its cell widened by one cell on every side, so that
// a crossing in a cell the surface only clips is still found.
constexpr int kNodeReach = 1;
// Each RAMLS fit uses only the points facing within 120° of the nearest point's normal. Where a
// stretched sheet is thinner than the 3h support, both of its sides fall in one neighbourhood;
// their opposite normals cancel in a shared fit and spurious crossings multiply (Enright's test
// exploded at t ≈ 1.8 without this). 120° keeps the 90° corners of the Zalesak slot whole.
constexpr double kSideCosine = -0.5;

class ZalesakField final : public VelocityField {
 public:
  Vec3d At(const Vec3d& x, double) const override {
    constexpr double w = std::numbers::pi / 314.0;
    return {w * (0.5 - x.y()), w * (x.x() - 0.5), 0.0};
  }
};

class EnrightField final : public VelocityField {
 public:
  EnrightField(double period, TimeModulation modulation) : period_(period), modulation_(modulation) {}
  double Modulation(double t) const {
    if (modulation_ == TimeModulation::kCosine) return std::cos(std::numbers::pi * t / period_);
    const double from_half = t - 0.5 * period_;
    if (std::abs(from_half) <= 1e-9 * period_) return 0;
    return from_half < 0 ? 1 : -1;
  }
  Vec3d At(const Vec3d& p, double t) const override {
    const double pi = std::numbers::pi, c = Modulation(t);
    const double sx = std::sin(pi * p.x()), sy = std::sin(pi * p.y()), sz = std::sin(pi * p.z());
    const double s2x = std::sin(2 * pi * p.x()), s2y = std::sin(2 * pi * p.y()), s2z = std::sin(2 * pi * p.z());
    return {2 * sx * sx * s2y * s2z * c, -s2x * sy * sy * s2z * c, -s2x * s2y * sz * sz * c};
  }

 private:
  double period_;
  TimeModulation modulation_;
};

class GridField final : public VelocityField {
 public:
  GridField(Vec3d origin, Vec3d spacing, int nx, int ny, int nz, std::vector<Vec3d> values)
      : origin_(origin), spacing_(spacing), n_{nx, ny, nz}, values_(std::move(values)) {}
  Vec3d At(const Vec3d& x, double) const override {
    std::array<int, 3> i0{};
    std::array<double, 3> f{};
    for (int a = 0; a < 3; ++a) {
      const double g = std::clamp((x[a] - origin_[a]) / spacing_[a], 0.0, static_cast<double>(n_[a] - 1));
      i0[a] = std::min(static_cast<int>(g), std::max(0, n_[a] - 2));
      f[a] = n_[a] > 1 ? g - i0[a] : 0.0;
    }
    Vec3d v = Vec3d::Zero();
    for (int corner = 0; corner < 8; ++corner) {
      double w = 1;
      std::array<int, 3> i{};
      for (int a = 0; a < 3; ++a) {
        const int bit = (corner >> a) & 1;
        i[a] = std::min(i0[a] + bit, n_[a] - 1);
        w *= bit ? f[a] : 1 - f[a];
      }
      if (w == 0) continue;
      v += w * values_[static_cast<size_t>(i[0]) +
                       static_cast<size_t>(n_[0]) *
                           (static_cast<size_t>(i[1]) + static_cast<size_t>(n_[1]) * static_cast<size_t>(i[2]))];
    }
    return v;
  }

 private:
  Vec3d origin_;
  Vec3d spacing_;
  std::array<int, 3> n_;
  std::vector<Vec3d> values_;
};

Vec3d ShapeCentre(InitialShape shape) {
  return shape == InitialShape::kSphere ? Vec3d(0.35, 0.35, 0.35) : Vec3d(0.5, 0.75, 0.5);
}

// The exact benchmark shapes as implicit functions (distance-like, exact gradient almost
// everywhere), for the initial sampling.
class ShapeField final : public core::ImplicitFunction {
 public:
  explicit ShapeField(InitialShape shape) : shape_(shape) {}
  core::FieldValue Value(const Vec3d& x) const override { return {Eval(x, nullptr), true}; }
  core::FieldGradient ValueAndGradient(const Vec3d& x) const override {
    core::FieldGradient g;
    g.value = Eval(x, &g.gradient);
    g.defined = true;
    return g;
  }

 private:
  double Eval(const Vec3d& x, Vec3d* gradient) const {
    const Vec3d centre = ShapeCentre(shape_);
    const Vec3d d = x - centre;
    const double sphere = d.norm() - kRadius;
    if (gradient) *gradient = d.norm() > 0 ? Vec3d(d.normalized()) : Vec3d::UnitZ();
    if (shape_ == InitialShape::kSphere) return sphere;
    // The slot: |x − 0.5| ≤ 0.025, y ≤ 0.725, any z; F = max(sphere, −slot) (sphere minus slot).
    const double half_width = 0.025, top = 0.725;
    const double qx = std::abs(x.x() - 0.5) - half_width, qy = x.y() - top;
    const double slot = qx > 0 && qy > 0 ? std::hypot(qx, qy) : std::max(qx, qy);  // < 0 inside the slot.
    if (-slot > sphere) {
      if (gradient) {
        if (qx > 0 && qy > 0) {
          *gradient = -Vec3d((x.x() > 0.5 ? 1 : -1) * qx, qy, 0).normalized();
        } else if (qx > qy) {
          *gradient = Vec3d(x.x() > 0.5 ? -1 : 1, 0, 0);
        } else {
          *gradient = Vec3d(0, -1, 0);
        }
      }
      return -slot;
    }
    return sphere;
  }
  InitialShape shape_;
};

// Grid nodes are integer triples (i, j, k) at i·h; keys pack them like J1a vertex keys.
using NodeKey = uint64_t;
NodeKey Key(uint32_t i, uint32_t j, uint32_t k) { return extract::PackVertex(i, j, k); }

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
                                               double h, bool z_only, core::JobContext& ctx) {
  std::vector<core::FieldValue> values(nodes.size());
  absl::flat_hash_map<NodeKey, uint32_t> index;
  index.reserve(nodes.size());
  for (uint32_t n = 0; n < nodes.size(); ++n) index.emplace(nodes[n], n);
  auto position = [&](NodeKey key) {
    const auto [i, j, k] = extract::UnpackVertex(key);
    return Vec3d(i * h, j * h, k * h);
  };
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      nodes.size(), 256,
      [&](size_t b, size_t e) {
        for (size_t n = b; n < e; ++n) values[n] = field.Value(position(nodes[n]));
      },
      &ctx));
  constexpr uint32_t kNone = std::numeric_limits<uint32_t>::max();
  std::vector<std::array<Crossing, 3>> found(nodes.size());
  std::vector<std::array<char, 3>> has(nodes.size(), {0, 0, 0});
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      nodes.size(), 256,
      [&](size_t b, size_t e) {
        for (size_t n = b; n < e; ++n) {
          const core::FieldValue& va = values[n];
          if (!va.defined || std::isnan(va.value)) continue;
          const auto [i, j, k] = extract::UnpackVertex(nodes[n]);
          for (int axis = z_only ? 2 : 0; axis < 3; ++axis) {
            const NodeKey next = Key(i + (axis == 0), j + (axis == 1), k + (axis == 2));
            const auto it = index.find(next);
            const uint32_t m = it == index.end() ? kNone : it->second;
            if (m == kNone) continue;
            const core::FieldValue& vb = values[m];
            if (!vb.defined || std::isnan(vb.value) || (va.value < 0) == (vb.value < 0)) continue;
            const Vec3d from = position(nodes[n]), to = position(next);
            const Vec3d root =
                from + core::RefineRootOnSegment(field, from, to, va.value, vb.value, kRootSteps) * (to - from);
            const core::FieldGradient g = field.ValueAndGradient(root);
            const double length = g.gradient.norm();
            if (!(length > 0) || std::abs(g.value) > kRootResidual * h * length) continue;
            found[n][static_cast<size_t>(axis)] = {root.cast<float>(), (g.gradient / length).cast<float>()};
            has[n][static_cast<size_t>(axis)] = 1;
          }
        }
      },
      &ctx));
  GridlineResult out;
  for (size_t n = 0; n < nodes.size(); ++n) {
    for (int axis = 0; axis < 3; ++axis) {
      if (!has[n][static_cast<size_t>(axis)]) continue;
      const Crossing& c = found[n][static_cast<size_t>(axis)];
      out.crossings.push_back(c);
      if (axis == 2) {
        const auto [i, j, k] = extract::UnpackVertex(nodes[n]);
        out.z_crossings.push_back({uint64_t{i} | (uint64_t{j} << 32), c.point.z(), values[n].value > 0});
      }
    }
  }
  std::sort(out.z_crossings.begin(), out.z_crossings.end(), [](const ZCrossing& a, const ZCrossing& b) {
    return a.column != b.column ? a.column < b.column : a.z < b.z;
  });
  return out;
}

// Inside intervals along each z gridline column: an entering crossing opens one, the next
// leaving crossing closes it (unpaired crossings, where the front is open, add nothing).
template <typename Visit>
void ForEachInsideInterval(std::span<const ZCrossing> z, Visit&& visit) {
  for (size_t a = 0; a < z.size();) {
    size_t b = a;
    while (b < z.size() && z[b].column == z[a].column) ++b;
    double open = std::numeric_limits<double>::quiet_NaN();
    for (size_t c = a; c < b; ++c) {
      if (z[c].entering) {
        open = z[c].z;
      } else if (!std::isnan(open)) {
        visit(z[a].column, open, z[c].z);
        open = std::numeric_limits<double>::quiet_NaN();
      }
    }
    a = b;
  }
}

double VolumeOf(std::span<const ZCrossing> z, double h) {
  double length = 0;
  ForEachInsideInterval(z, [&](uint64_t, double lo, double hi) { length += hi - lo; });
  return length * h * h;
}

int GridCells(double h) { return static_cast<int>(std::lround(1.0 / h)); }

// The grid nodes within kNodeReach cells of any point, sorted. `marks` is a reusable dense
// bitmap of the (n+1)³ nodes (one bit each: 17 MB at h = 1/512, 135 MB on the h/2 grid of the
// shape error), left cleared.
std::vector<NodeKey> NodesNear(std::span<const Vec3f> points, double h, std::vector<bool>& marks) {
  const int n = GridCells(h);
  const auto side = static_cast<size_t>(n + 1);
  if (marks.size() != side * side * side) marks.assign(side * side * side, false);
  std::vector<NodeKey> nodes;
  std::vector<size_t> touched;
  for (const Vec3f& p : points) {
    std::array<int, 3> c{};
    for (int a = 0; a < 3; ++a) c[a] = static_cast<int>(std::floor(p[a] / h));
    for (int dz = -kNodeReach; dz <= kNodeReach + 1; ++dz) {
      const int k = c[2] + dz;
      if (k < 0 || k > n) continue;
      for (int dy = -kNodeReach; dy <= kNodeReach + 1; ++dy) {
        const int j = c[1] + dy;
        if (j < 0 || j > n) continue;
        for (int dx = -kNodeReach; dx <= kNodeReach + 1; ++dx) {
          const int i = c[0] + dx;
          if (i < 0 || i > n) continue;
          const size_t cell = static_cast<size_t>(i) + side * (static_cast<size_t>(j) + side * static_cast<size_t>(k));
          if (marks[cell]) continue;
          marks[cell] = true;
          touched.push_back(cell);
          nodes.push_back(Key(static_cast<uint32_t>(i), static_cast<uint32_t>(j), static_cast<uint32_t>(k)));
        }
      }
    }
  }
  for (size_t cell : touched) marks[cell] = false;
  std::sort(nodes.begin(), nodes.end());
  return nodes;
}

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
Front Thin(const std::vector<Crossing>& crossings, double h) {
  SpacingGrid kept(0.5 * h);
  Front front;
  for (const Crossing& c : crossings) {
    if (kept.HasNear(c.point, c.normal, 0.5 * h)) continue;
    kept.Add(c.point, c.normal);
    front.points.push_back(c.point);
    front.normals.push_back(c.normal);
  }
  return front;
}

absl::StatusOr<std::unique_ptr<mls::AlgebraicMlsFunction>> FrontFunction(const Front& front, double h,
                                                                         double support_factor, core::JobContext& ctx) {
  core::PointCloud cloud;
  cloud.positions = front.points;
  cloud.normals = front.normals;
  mls::AlgebraicMlsParams p;
  p.spacing = h;
  p.support_factor = support_factor;
  p.side_cosine = kSideCosine;
  return mls::BuildAlgebraicMls(cloud, p, ctx);
}

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
                                                                        core::JobContext& ctx) {
  auto fit = FrontFunction(front, h, support_factor, ctx);
  if (!fit.ok()) return fit.status();
  if (merge_distance <= 0) return std::unique_ptr<core::ImplicitFunction>(std::move(*fit));
  return std::unique_ptr<core::ImplicitFunction>(
      std::make_unique<TopologyField>(*std::move(fit), 2 * merge_distance * h));
}

// Marker points carry the step they were made at; older markers have been moved by the exact
// flow for longer and outrank younger ones when two crowd each other.
struct Markers {
  Front front;
  std::vector<int> birth;
};

// Drops every marker that an older (or, at equal age, earlier) kept marker facing the same way
// lies within `min_distance` of.
void ThinMarkers(Markers& m, double min_distance) {
  std::vector<uint32_t> order(m.front.points.size());
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return m.birth[a] < m.birth[b]; });
  SpacingGrid kept(min_distance);
  std::vector<char> keep(order.size(), 0);
  for (uint32_t i : order) {
    if (kept.HasNear(m.front.points[i], m.front.normals[i], min_distance)) continue;
    kept.Add(m.front.points[i], m.front.normals[i]);
    keep[i] = 1;
  }
  Markers out;
  for (size_t i = 0; i < keep.size(); ++i) {
    if (!keep[i]) continue;
    out.front.points.push_back(m.front.points[i]);
    out.front.normals.push_back(m.front.normals[i]);
    out.birth.push_back(m.birth[i]);
  }
  m = std::move(out);
}

// Adds each candidate as a marker born at `step` unless a marker facing the same way (in `grid`,
// which the new ones join) lies within `spacing` of it.
void AddMarkersApart(std::span<const Crossing> candidates, double spacing, int step, SpacingGrid& grid, Markers& m) {
  for (const Crossing& c : candidates) {
    if (grid.HasNear(c.point, c.normal, spacing)) continue;
    grid.Add(c.point, c.normal);
    m.front.points.push_back(c.point);
    m.front.normals.push_back(c.normal);
    m.birth.push_back(step);
  }
}

// Where the flow has stretched the markers apart, adds new ones. The midpoint of two markers
// facing the same way (within 60°) and at most 2h apart, with no marker facing that way within
// `gap` of it, is projected onto the RAMLS surface fitted to that side alone (the markers facing
// within 90° of the pair), so the two faces of a sheet never mix however thin it is. Midpoints
// only interpolate: a spot beyond the last marker, at a sheet's rim, is never made up. A
// projection that does not settle on the surface within h/2 is dropped.
absl::Status FillGaps(Markers& m, int step, double h, double gap, double support_factor, core::JobContext& ctx) {
  constexpr int kProjections = 3;
  constexpr double kPairCosine = 0.5;
  const double reach = 2 * h;
  auto field = FrontFunction(m.front, h, support_factor, ctx);
  if (!field.ok()) return field.status();
  const core::KdTree tree(m.front.points);
  SpacingGrid grid(gap);
  for (size_t i = 0; i < m.front.points.size(); ++i) grid.Add(m.front.points[i], m.front.normals[i]);
  const size_t n = m.front.points.size();
  std::vector<std::vector<Crossing>> spots(n);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 256,
      [&](size_t b, size_t e) {
        std::vector<core::Neighbor> near;
        for (size_t i = b; i < e; ++i) {
          const Vec3f& pi = m.front.points[i];
          const Vec3f& ni = m.front.normals[i];
          tree.Radius(pi, static_cast<float>(reach), near);
          for (const core::Neighbor& q : near) {
            if (q.index <= i || q.distance2 < 4 * gap * gap) continue;
            const Vec3f& nj = m.front.normals[q.index];
            if (ni.dot(nj) < kPairCosine) continue;
            const Vec3d mid = 0.5 * (pi + m.front.points[q.index]).cast<double>();
            const Vec3d facing = (ni + nj).cast<double>().normalized();
            if (grid.HasNear(mid.cast<float>(), facing.cast<float>(), gap)) continue;
            Vec3d x = mid;
            core::FieldGradient g;
            bool ok = true;
            for (int it = 0; it <= kProjections && ok; ++it) {
              g = (*field)->ValueAndGradientFacing(x, facing, 0.0);
              const double g2 = g.gradient.squaredNorm();
              ok = g.defined && g2 > 0;
              if (ok && it < kProjections) x -= g.value / g2 * g.gradient;
            }
            if (!ok || !x.allFinite() || std::abs(g.value) > 1e-3 * h || (x - mid).norm() > 0.5 * h) continue;
            const Vec3d fitted = g.gradient.normalized();
            if (fitted.dot(facing) < kPairCosine) continue;  // The fit turned away from its own side.
            spots[i].push_back({x.cast<float>(), fitted.cast<float>()});
          }
        }
      },
      &ctx));
  for (const std::vector<Crossing>& around : spots) AddMarkersApart(around, gap, step, grid, m);
  return absl::OkStatus();
}

// The markers mode's topology changes: the markers where the blend of TopologyField changes F
// (two sides within the blend radius of each other, or one front inside another) go, and the
// gridline roots of the blended F around them, thinned against the markers that stay, take
// their place.
absl::Status ReplaceMergingMarkers(Markers& m, int step, double h, double support_factor, double merge_distance,
                                   std::vector<bool>& marks, core::JobContext& ctx) {
  auto fit = FrontFunction(m.front, h, support_factor, ctx);
  if (!fit.ok()) return fit.status();
  const TopologyField field(*std::move(fit), 2 * merge_distance * h);
  std::vector<char> merging(m.front.points.size(), 0);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      merging.size(), 512,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) merging[i] = field.BlendActsAt(m.front.points[i].cast<double>());
      },
      &ctx));
  std::vector<Vec3f> replaced;
  Markers kept;
  for (size_t i = 0; i < merging.size(); ++i) {
    if (merging[i]) {
      replaced.push_back(m.front.points[i]);
      continue;
    }
    kept.front.points.push_back(m.front.points[i]);
    kept.front.normals.push_back(m.front.normals[i]);
    kept.birth.push_back(m.birth[i]);
  }
  if (replaced.empty()) return absl::OkStatus();
  const double fine = 0.5 * h;
  auto sampled = SampleGridlines(field, NodesNear(replaced, fine, marks), fine, false, ctx);
  if (!sampled.ok()) return sampled.status();
  SpacingGrid grid(0.5 * h);
  for (size_t i = 0; i < kept.front.points.size(); ++i) grid.Add(kept.front.points[i], kept.front.normals[i]);
  AddMarkersApart(sampled->crossings, 0.5 * h, step, grid, kept);
  m = std::move(kept);
  return absl::OkStatus();
}

// The z-gridline crossings, on a grid of spacing `grid`, of the RAMLS function (spacing h) of
// the front: what the volume and the shape error are measured from.
absl::StatusOr<std::vector<ZCrossing>> ZCrossings(const Front& front, double h, double grid, double support_factor,
                                                  double merge_distance, std::vector<bool>& marks,
                                                  core::JobContext& ctx) {
  auto field = SurfaceFunction(front, h, support_factor, merge_distance, ctx);
  if (!field.ok()) return field.status();
  auto sampled = SampleGridlines(**field, NodesNear(front.points, grid, marks), grid, true, ctx);
  if (!sampled.ok()) return sampled.status();
  return std::move(sampled->z_crossings);
}

absl::Status ValidateSpacing(double h) {
  if (!std::isfinite(h) || h < 1.0 / 512 - 1e-12 || h > 1.0 / 8 + 1e-12) {
    return absl::InvalidArgumentError(core::StrCat("h must be in [1/512, 1/8] (the unit cube's grid), got ", h));
  }
  if (std::abs(1.0 / h - std::round(1.0 / h)) > 1e-6 * (1.0 / h)) {
    return absl::InvalidArgumentError(
        core::StrCat("h must divide the unit cube: 1/h must be a whole number, got 1/h = ", 1.0 / h));
  }
  return absl::OkStatus();
}

// The largest eigenvalue of the symmetric part of ∇v: the fastest rate at which the flow pulls
// two nearby points apart (d|δ|/dt ≤ λ|δ|).
double LargestStrainRate(const Eigen::Matrix3d& jacobian) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
  solver.computeDirect(0.5 * (jacobian + jacobian.transpose()), Eigen::EigenvaluesOnly);
  return solver.eigenvalues()(2);
}

void RaiseTo(std::atomic<double>& most, double value) {
  double seen = most.load();
  while (value > seen && !most.compare_exchange_weak(seen, value)) {
  }
}

// Flow Jacobian ∇v by central differences (the fields are smooth; the step only has to be far
// below their length scale and far above rounding).
Eigen::Matrix3d Jacobian(const VelocityField& v, const Vec3d& x, double t) {
  constexpr double eps = 1e-6;
  Eigen::Matrix3d j;
  for (int a = 0; a < 3; ++a) {
    const Vec3d e = Vec3d::Unit(a) * eps;
    j.col(a) = (v.At(x + e, t) - v.At(x - e, t)) / (2 * eps);
  }
  return j;
}

}  // namespace

double ShapeValue(InitialShape shape, const Vec3d& x) { return ShapeField(shape).Value(x).value; }

Vec3d Rk4Step(const VelocityField& v, const Vec3d& x, double t, double dt) {
  const Vec3d k1 = v.At(x, t);
  const Vec3d k2 = v.At(x + 0.5 * dt * k1, t + 0.5 * dt);
  const Vec3d k3 = v.At(x + 0.5 * dt * k2, t + 0.5 * dt);
  const Vec3d k4 = v.At(x + dt * k3, t + dt);
  return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4);
}

std::unique_ptr<VelocityField> ZalesakRotation() { return std::make_unique<ZalesakField>(); }
std::unique_ptr<VelocityField> EnrightDeformation(double period, TimeModulation modulation) {
  return std::make_unique<EnrightField>(period, modulation);
}

absl::StatusOr<std::unique_ptr<VelocityField>> GridVelocity(Vec3d origin, Vec3d spacing, int nx, int ny, int nz,
                                                            std::vector<Vec3d> values) {
  if (!origin.allFinite() || !spacing.allFinite() || !(spacing.minCoeff() > 0)) {
    return absl::InvalidArgumentError("the velocity grid needs a finite origin and a positive spacing along each axis");
  }
  if (nx < 1 || ny < 1 || nz < 1 || static_cast<int64_t>(nx) * ny * nz > 256LL * 256 * 256) {
    return absl::InvalidArgumentError("the velocity grid must have 1..256³ nodes");
  }
  if (values.size() != static_cast<size_t>(nx) * static_cast<size_t>(ny) * static_cast<size_t>(nz)) {
    return absl::InvalidArgumentError(core::StrCat(
        "the velocity grid has ", values.size(), " vectors, expected nx·ny·nz = ", static_cast<int64_t>(nx) * ny * nz));
  }
  for (size_t i = 0; i < values.size(); ++i) {
    if (!values[i].allFinite()) return absl::InvalidArgumentError(core::StrCat("velocity ", i, " is not finite"));
  }
  return std::make_unique<GridField>(origin, spacing, nx, ny, nz, std::move(values));
}

const core::ParamTable<TrackingParams>& TrackingParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<TrackingParams>();
    t->Real<&TrackingParams::h>("h", 1.0 / 512, 1.0 / 8, "unit-cube lengths",
                                "background grid spacing; 1/h must be whole")
        .Real<&TrackingParams::dt>("dt", 1e-6, 1000, "time units", "time step")
        .Integer<&TrackingParams::steps>("steps", 1, 100000, "", "number of steps")
        .Integer<&TrackingParams::output_stride>("stride", 1, 100000, "steps",
                                                 "write a frame every this many steps (and after the last)")
        .Real<&TrackingParams::support_factor>("support_factor", 1.5, 10, "h", "RAMLS support radius")
        .Choice<&TrackingParams::resampling>(
            "resampling",
            {{"markers", static_cast<int>(Resampling::kMarkers),
              "the advected points stay; crowded ones are thinned, stretched gaps filled from the RAMLS surface of "
              "their side; keeps sheets thinner than h"},
             {"gridlines", static_cast<int>(Resampling::kGridlines),
              "the seed's re-generation of the whole front on the gridlines (see regeneration_stretch)"}},
            "how the front stays sampled after each step")
        .Real<&TrackingParams::marker_spacing>("marker_spacing", 0.1, 1, "h",
                                               "markers: of two markers facing the same way closer than this, the "
                                               "younger goes")
        .Real<&TrackingParams::marker_gap>("marker_gap", 0.15, 1, "h",
                                           "markers: a midpoint of two markers with no marker within this gets a "
                                           "new one; must exceed marker_spacing")
        .Real<&TrackingParams::merge_distance>("merge_distance", 0, 5, "h",
                                               "fronts closer than this merge and necks thinner than it pinch off; at "
                                               "most support_factor/2; 1.25-1.5 with the default support; 0 keeps "
                                               "every thin sheet and gap")
        .Real<&TrackingParams::regeneration_stretch>(
            "regeneration_stretch", 1, 4, "",
            "gridlines: re-generate the front once the flow may have spread neighbouring points by this factor; 1 = "
            "every step (the seed's literal scheme)")
        .Integer<&TrackingParams::max_points>("max_points", 100, 50'000'000, "points",
                                              "stop with an error if the front grows past this many points")
        .AddRule([](const TrackingParams& p) { return ValidateSpacing(p.h); })
        .AddRule([](const TrackingParams& p) {
          // The blend compares the two sides' fits over 2·merge_distance·h; only the support
          // sees both, so a wider blend would switch on and off at the support's edge.
          return 2 * p.merge_distance <= p.support_factor + 1e-12
                     ? absl::OkStatus()
                     : absl::InvalidArgumentError(
                           core::StrCat("merge_distance=", p.merge_distance,
                                        " may be at most half of support_factor=", p.support_factor));
        })
        .AddRule([](const TrackingParams& p) {
          return p.marker_gap > p.marker_spacing
                     ? absl::OkStatus()
                     : absl::InvalidArgumentError(
                           core::StrCat("marker_gap=", p.marker_gap, " must exceed marker_spacing=", p.marker_spacing));
        });
    return t;
  }();
  return *table;
}

absl::Status Validate(const TrackingParams& p) { return TrackingParamTable().Validate(p); }

absl::StatusOr<Front> SampleInitialFront(InitialShape shape, double h) {
  const Vec3d centre = ShapeCentre(shape);
  return SampleFront(ShapeField(shape), centre - Vec3d::Constant(kRadius), centre + Vec3d::Constant(kRadius), h);
}

absl::StatusOr<Front> SampleFront(const core::ImplicitFunction& shape, const Vec3d& box_lo, const Vec3d& box_hi,
                                  double h) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpacing(h));
  if (!box_lo.allFinite() || !box_hi.allFinite() || !(box_lo.array() <= box_hi.array()).all()) {
    return absl::InvalidArgumentError("the sampling box needs finite corners with lo <= hi");
  }
  std::vector<NodeKey> nodes;
  const int n = GridCells(h);
  std::array<int, 3> lo{}, hi{};
  for (int a = 0; a < 3; ++a) {
    lo[a] = std::clamp(static_cast<int>(std::floor(std::clamp(box_lo[a], 0.0, 1.0) / h)) - 2, 0, n);
    hi[a] = std::clamp(static_cast<int>(std::ceil(std::clamp(box_hi[a], 0.0, 1.0) / h)) + 2, 0, n);
  }
  for (int k = lo[2]; k <= hi[2]; ++k) {
    for (int j = lo[1]; j <= hi[1]; ++j) {
      for (int i = lo[0]; i <= hi[0]; ++i) {
        nodes.push_back(Key(static_cast<uint32_t>(i), static_cast<uint32_t>(j), static_cast<uint32_t>(k)));
      }
    }
  }
  std::sort(nodes.begin(), nodes.end());
  core::LocalJobContext ctx;
  auto sampled = SampleGridlines(shape, nodes, h, false, ctx);
  if (!sampled.ok()) return sampled.status();
  if (sampled->crossings.empty()) {
    return absl::FailedPreconditionError("the shape has no surface inside the sampling box");
  }
  return Thin(sampled->crossings, h);
}

absl::StatusOr<double> FrontVolume(const Front& front, double h, double support_factor, double merge_distance) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpacing(h));
  core::LocalJobContext ctx;
  std::vector<bool> marks;
  auto z = ZCrossings(front, h, h, support_factor, merge_distance, marks, ctx);
  if (!z.ok()) return z.status();
  return VolumeOf(*z, h);
}

absl::StatusOr<core::TriangleMesh> FrontMesh(const Front& front, double h, core::JobContext& ctx, double support_factor,
                                             double merge_distance) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpacing(h));
  auto field = SurfaceFunction(front, h, support_factor, merge_distance, ctx);
  if (!field.ok()) return field.status();
  extract::IsosurfaceParams p;
  p.cell_size = h;
  auto extracted = extract::ExtractIsosurface(**field, front.points, p, ctx);
  if (!extracted.ok()) return extracted.status();
  return std::move(extracted->mesh);
}

absl::StatusOr<double> ShapeError(const Front& front, InitialShape exact, double h, double support_factor,
                                  double merge_distance) {
  LSQSURF_RETURN_IF_ERROR(ValidateSpacing(h));
  core::LocalJobContext ctx;
  const double fine = 0.5 * h;
  std::vector<bool> marks;
  auto crossings = ZCrossings(front, h, fine, support_factor, merge_distance, marks, ctx);
  if (!crossings.ok()) return crossings.status();
  // Inside intervals of the front per column, then of the exact shape (a sphere's chord, or
  // nothing across the slot), and the length of their symmetric difference.
  absl::flat_hash_map<uint64_t, std::vector<std::pair<double, double>>> front_intervals;
  ForEachInsideInterval(*crossings, [&](uint64_t column, double lo, double hi) {
    front_intervals[column].push_back({lo, hi});
  });
  const Vec3d centre = ShapeCentre(exact);
  auto exact_interval = [&](double x, double y) -> std::vector<std::pair<double, double>> {
    const double r2 = kRadius * kRadius - (x - centre.x()) * (x - centre.x()) - (y - centre.y()) * (y - centre.y());
    if (r2 <= 0) return {};
    if (exact == InitialShape::kZalesakSphere && std::abs(x - 0.5) <= 0.025 && y <= 0.725) return {};
    return {{centre.z() - std::sqrt(r2), centre.z() + std::sqrt(r2)}};
  };
  auto symmetric_difference = [](std::vector<std::pair<double, double>> a, std::vector<std::pair<double, double>> b) {
    // Sweep over all interval ends; the measure where exactly one side is inside.
    std::vector<std::pair<double, int>> events;
    for (auto [lo, hi] : a) events.push_back({lo, 1}), events.push_back({hi, -1});
    for (auto [lo, hi] : b) events.push_back({lo, 2}), events.push_back({hi, -2});
    std::sort(events.begin(), events.end());
    int in_a = 0, in_b = 0;
    double length = 0, last = 0;
    for (auto [z, e] : events) {
      if ((in_a > 0) != (in_b > 0)) length += z - last;
      last = z;
      if (std::abs(e) == 1)
        in_a += e;
      else
        in_b += e / 2;
    }
    return length;
  };
  const int cells = GridCells(fine);
  double e1 = 0;
  for (int j = 0; j <= cells; ++j) {
    for (int i = 0; i <= cells; ++i) {
      const uint64_t column = static_cast<uint64_t>(i) | (static_cast<uint64_t>(j) << 32);
      const auto it = front_intervals.find(column);
      auto ex = exact_interval(i * fine, j * fine);
      if (it == front_intervals.end() && ex.empty()) continue;
      e1 +=
          symmetric_difference(it == front_intervals.end() ? std::vector<std::pair<double, double>>{} : it->second, ex);
    }
  }
  return e1 * fine * fine;
}

absl::Status Track(const Front& initial, const VelocityField& velocity, const TrackingParams& params,
                   core::JobContext& ctx,
                   const std::function<absl::Status(const FrameStats&, const Front&)>& on_frame) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (initial.points.size() < 4 || initial.normals.size() != initial.points.size()) {
    return absl::InvalidArgumentError("the initial front needs at least 4 points, each with a normal");
  }
  const double h = params.h, dt = params.dt;
  std::vector<bool> marks;
  Markers markers{initial, std::vector<int>(initial.points.size(), 0)};
  Front& front = markers.front;
  auto z0 = ZCrossings(front, h, h, params.support_factor, params.merge_distance, marks, ctx);
  if (!z0.ok()) return z0.status();
  const double v0 = VolumeOf(*z0, h);
  if (!(v0 > 0))
    return absl::InvalidArgumentError(
        "the initial front encloses no volume on the grid; is it closed and oriented outward?");
  FrameStats stats;
  stats.points = front.points.size();
  stats.volume = v0;
  LSQSURF_RETURN_IF_ERROR(on_frame(stats, front));
  auto since = std::chrono::steady_clock::now();
  const bool gridlines = params.resampling == Resampling::kGridlines;
  double log_stretch = 0;  // ∫ λ dt since the last re-generation (gridlines).
  for (int step = 1; step <= params.steps; ++step) {
    const double t = (step - 1) * dt;
    // 1. Advection (RK4) and normal transport; in the gridline mode also the largest strain rate.
    std::atomic<bool> finite{true};
    std::atomic<double> strain_rate{0};
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        front.points.size(), 512,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i) {
            const Vec3d p = front.points[i].cast<double>();
            const Vec3d moved = Rk4Step(velocity, p, t, dt);
            const Vec3d n = front.normals[i].cast<double>();
            const Eigen::Matrix3d jacobian = Jacobian(velocity, 0.5 * (p + moved), t + 0.5 * dt);
            const Vec3d turned = n - dt * jacobian.transpose() * n;
            if (gridlines) RaiseTo(strain_rate, LargestStrainRate(jacobian));
            if (!moved.allFinite() || !turned.allFinite() || !(turned.norm() > 0)) {
              finite = false;
              continue;
            }
            front.points[i] = moved.cast<float>();
            front.normals[i] = turned.normalized().cast<float>();
          }
        },
        &ctx));
    if (!finite) {
      return absl::InvalidArgumentError(core::StrCat("the velocity field gave a non-finite value at step ", step));
    }
    std::vector<ZCrossing> z_crossings;
    log_stretch += strain_rate.load() * dt;
    // Topology changes happen at re-generations, so with merge_distance every step is one: two
    // fronts that merely translate towards each other never stretch.
    // (λ ≥ 0, so regeneration_stretch = 1 re-generates every step.)
    const bool regenerate =
        gridlines && (params.merge_distance > 0 || log_stretch >= std::log(params.regeneration_stretch));
    if (regenerate) {
      // 2. Re-generation on the gridlines, 3. thinning.
      log_stretch = 0;
      auto field = SurfaceFunction(front, h, params.support_factor, params.merge_distance, ctx);
      if (!field.ok()) return field.status();
      auto sampled = SampleGridlines(**field, NodesNear(front.points, h, marks), h, false, ctx);
      if (!sampled.ok()) return sampled.status();
      front = Thin(sampled->crossings, h);
      markers.birth.assign(front.points.size(), step);
      z_crossings = std::move(sampled->z_crossings);
    } else if (!gridlines) {
      // 2. Markers that crowd are thinned, 3. gaps are filled.
      ThinMarkers(markers, params.marker_spacing * h);
      LSQSURF_RETURN_IF_ERROR(FillGaps(markers, step, h, params.marker_gap * h, params.support_factor, ctx));
      if (params.merge_distance > 0) {
        LSQSURF_RETURN_IF_ERROR(
            ReplaceMergingMarkers(markers, step, h, params.support_factor, params.merge_distance, marks, ctx));
      }
    }
    if (front.points.size() < 4) {
      return absl::FailedPreconditionError(
          core::StrCat("the front vanished at step ", step, ": it became thinner than the grid spacing h"));
    }
    if (front.points.size() > params.max_points) {
      return absl::ResourceExhaustedError(core::StrCat("the front grew to ", front.points.size(), " points at step ",
                                                       step, " (limit ", params.max_points,
                                                       "); a finer h resolves thin sheets"));
    }
    ctx.ReportProgress("tracking the front", static_cast<double>(step) / params.steps);
    if (step % params.output_stride == 0 || step == params.steps) {
      stats.step = step;
      stats.time = step * dt;
      stats.points = front.points.size();
      if (!regenerate) {
        auto z = ZCrossings(front, h, h, params.support_factor, params.merge_distance, marks, ctx);
        if (!z.ok()) return z.status();
        z_crossings = std::move(*z);
      }
      stats.volume = VolumeOf(z_crossings, h);
      stats.volume_change = (stats.volume - v0) / v0;
      stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
      LSQSURF_RETURN_IF_ERROR(on_frame(stats, front));
      since = std::chrono::steady_clock::now();
    }
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::front
