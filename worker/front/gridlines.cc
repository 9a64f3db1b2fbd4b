#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/isosurface.h"
#include "worker/front/front_internal.h"
#include "worker/front/front_tracking.h"

namespace lsqsurf::front {
namespace {

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

int GridCells(double h) { return static_cast<int>(std::lround(1.0 / h)); }

}  // namespace

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

double VolumeOf(std::span<const ZCrossing> z, double h) {
  double length = 0;
  ForEachInsideInterval(z, [&](uint64_t, double lo, double hi) { length += hi - lo; });
  return length * h * h;
}

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

double ShapeValue(InitialShape shape, const Vec3d& x) { return ShapeField(shape).Value(x).value; }

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

}  // namespace lsqsurf::front
