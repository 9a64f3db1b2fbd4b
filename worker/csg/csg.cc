#include "worker/csg/csg.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/j1a_isosurface.h"

namespace lsqsurf::csg {
namespace {

using core::Box3;
using core::FieldGradient;
using Mat3d = Eigen::Matrix3d;
using core::Vec3d;
using core::Vec3f;

// A similarity from world to a leaf's own coordinates: y = linear · x + offset, with
// linear = Rᵀ / scale; the leaf's world value is scale · f(y) (a distance stays a distance)
// and its world gradient R · ∇f(y).
struct Similarity {
  Mat3d rotation = Mat3d::Identity();
  Vec3d translation = Vec3d::Zero();  // World position of the leaf's origin.
  double scale = 1;

  Vec3d ToLocal(const Vec3d& x) const { return rotation.transpose() * (x - translation) / scale; }
  Vec3d ToWorld(const Vec3d& y) const { return rotation * (scale * y) + translation; }
  // Applies `inner` first, then this: the composition this ∘ inner.
  Similarity Then(const Similarity& inner) const {
    return {rotation * inner.rotation, ToWorld(inner.translation), scale * inner.scale};
  }
};

// Exact signed distances of the primitives in their own coordinates, with gradients.
double BoxDistance(const Vec3d& lo, const Vec3d& hi, const Vec3d& y, Vec3d* g) {
  const Vec3d c = (lo + hi) / 2, half = (hi - lo) / 2;
  const Vec3d d = y - c;
  const Vec3d q = d.cwiseAbs() - half;
  const Vec3d outside = q.cwiseMax(0.0);
  const double out_norm = outside.norm();
  if (out_norm > 0) {
    if (g) *g = (outside.array() * d.array().sign()).matrix() / out_norm;
    return out_norm;
  }
  int axis = 0;
  q.maxCoeff(&axis);
  if (g) *g = Vec3d::Unit(axis) * (d[axis] < 0 ? -1.0 : 1.0);
  return q[axis];
}

// 2D box distance of (radial, axial) excesses: exact for capped cylinders.
double CappedDistance(double radial, double axial, double* d_radial, double* d_axial) {
  const double ro = std::max(radial, 0.0), ao = std::max(axial, 0.0);
  const double out = std::hypot(ro, ao);
  if (out > 0) {
    *d_radial = ro / out, *d_axial = ao / out;
    return out;
  }
  const bool radial_wins = radial > axial;
  *d_radial = radial_wins ? 1 : 0, *d_axial = radial_wins ? 0 : 1;
  return std::max(radial, axial);
}

Vec3d AnyPerpendicular(const Vec3d& n) {
  const Vec3d t = std::abs(n.x()) < 0.9 ? Vec3d::UnitX() : Vec3d::UnitY();
  return n.cross(t).normalized();
}

struct Eval {
  double value = 0;
  Vec3d gradient = Vec3d::Zero();
  bool defined = true;
  int operand = -1;
};

}  // namespace

struct CsgFunction::Impl {
  struct Node {
    NodeKind kind = NodeKind::kUnion;
    std::vector<int> children;  // Operations.
    // Leaves: the world → own similarity and the primitive's data in its own coordinates.
    Similarity to_world;
    Vec3d a = Vec3d::Zero(), b = Vec3d::Zero(), axis = Vec3d::UnitZ();
    double r = 0, major = 0;
    const Operand* job = nullptr;
    Box3 cull;  // Jobs: outside this world box F is margin + the distance to it.
    double margin = 0;
    int operand = -1;
    Box3 bounds;  // World box holding the node's surface (empty box for none, all space for planes).
    bool unbounded = false;
  };
  std::vector<Node> nodes;  // nodes[0] is the root.
  std::vector<std::unique_ptr<Operand>> jobs;
  std::vector<int> leaves;  // Node of each operand.
  Box3 bounds;

  // Leaf value in world units at world x.
  Eval Leaf(const Node& n, const Vec3d& x, bool gradient) const {
    Eval e;
    e.operand = n.operand;
    if (n.job != nullptr && !n.cull.contains(x)) {
      const Vec3d nearest = x.cwiseMax(n.cull.min()).cwiseMin(n.cull.max());
      const double d = (x - nearest).norm();
      e.value = n.margin + d;
      if (gradient && d > 0) e.gradient = (x - nearest) / d;
      return e;
    }
    const Vec3d y = n.to_world.ToLocal(x);
    Vec3d g = Vec3d::Zero();
    Vec3d* gp = gradient ? &g : nullptr;
    double v = 0;
    switch (n.kind) {
      case NodeKind::kSphere: {
        const Vec3d d = y - n.a;
        const double len = d.norm();
        v = len - n.r;
        if (gp && len > 0) g = d / len;
        break;
      }
      case NodeKind::kBox: v = BoxDistance(n.a, n.b, y, gp); break;
      case NodeKind::kCylinder: {
        const Vec3d ab = n.b - n.a;
        const double length = ab.norm();
        const Vec3d u = ab / length;
        const Vec3d d = y - n.a;
        const double t = d.dot(u);
        const Vec3d radial = d - t * u;
        const double rho = radial.norm();
        double dr = 0, da = 0;
        v = CappedDistance(rho - n.r, std::abs(t - length / 2) - length / 2, &dr, &da);
        if (gp) {
          const Vec3d radial_dir = rho > 0 ? Vec3d(radial / rho) : AnyPerpendicular(u);
          g = dr * radial_dir + da * (t >= length / 2 ? 1.0 : -1.0) * u;
        }
        break;
      }
      case NodeKind::kTorus: {
        const Vec3d d = y - n.a;
        const double h = d.dot(n.axis);
        const Vec3d p = d - h * n.axis;
        const double rho = p.norm();
        const Vec3d ring_dir = rho > 0 ? Vec3d(p / rho) : AnyPerpendicular(n.axis);
        const Vec3d to_tube = (rho - n.major) * ring_dir + h * n.axis;
        const double len = to_tube.norm();
        v = len - n.r;
        if (gp && len > 0) g = to_tube / len;
        break;
      }
      case NodeKind::kPlane: {
        v = n.axis.dot(y - n.a);
        g = n.axis;
        break;
      }
      case NodeKind::kJob: {
        const FieldGradient fg = n.job->value(y, gradient);
        v = fg.value, g = fg.gradient, e.defined = fg.defined;
        // Outside its fitted region a PU function has no value: the solid is empty there.
        if (std::isnan(v)) v = n.margin, g = Vec3d::Zero(), e.defined = false;
        break;
      }
      default: break;
    }
    e.value = n.to_world.scale * v;
    if (gradient) e.gradient = n.to_world.rotation * g;
    return e;
  }

  Eval Evaluate(int index, const Vec3d& x, bool gradient) const {
    const Node& n = nodes[static_cast<size_t>(index)];
    if (n.kind != NodeKind::kUnion && n.kind != NodeKind::kIntersection && n.kind != NodeKind::kDifference) {
      return Leaf(n, x, gradient);
    }
    Eval best;
    for (size_t k = 0; k < n.children.size(); ++k) {
      Eval e = Evaluate(n.children[k], x, gradient);
      if (n.kind == NodeKind::kDifference && k > 0) e.value = -e.value, e.gradient = -e.gradient;
      const bool take = k == 0 || (n.kind == NodeKind::kUnion ? e.value < best.value : e.value > best.value);
      if (take) best = e;
    }
    return best;
  }

  // Builds node `index` (and below) from `src` under the similarity `outer`.
  absl::Status Add(const CsgNode& src, const Similarity& outer, const OperandResolver& resolve,
                   absl::flat_hash_map<std::string, int>& job_index) {
    switch (src.kind) {
      case NodeKind::kTranslate: {
        Similarity t;
        t.translation = src.Vector("t");
        return Add(src.children[0], outer.Then(t), resolve, job_index);
      }
      case NodeKind::kRotate: {
        const Vec3d c = src.Vector("c");
        Similarity r;
        r.rotation = Eigen::AngleAxisd(src.Number("deg") * M_PI / 180.0, src.Vector("axis").normalized()).matrix();
        r.translation = c - r.rotation * c;  // About c.
        return Add(src.children[0], outer.Then(r), resolve, job_index);
      }
      case NodeKind::kScale: {
        const Vec3d c = src.Vector("c");
        Similarity s;
        s.scale = src.Number("s");
        s.translation = c - s.scale * c;
        return Add(src.children[0], outer.Then(s), resolve, job_index);
      }
      default: break;
    }
    const int index = static_cast<int>(nodes.size());
    nodes.emplace_back();
    nodes.back().kind = src.kind;
    if (src.kind == NodeKind::kUnion || src.kind == NodeKind::kIntersection || src.kind == NodeKind::kDifference) {
      std::vector<int> children;
      for (const CsgNode& c : src.children) {
        children.push_back(static_cast<int>(nodes.size()));
        LSQSURF_RETURN_IF_ERROR(Add(c, outer, resolve, job_index));
      }
      Node& n = nodes[static_cast<size_t>(index)];
      n.children = children;
      CombineBounds(n);
      return absl::OkStatus();
    }
    Node leaf;
    leaf.kind = src.kind;
    leaf.to_world = outer;
    leaf.operand = static_cast<int>(leaves.size());
    Box3 own;  // In the leaf's own coordinates.
    switch (src.kind) {
      case NodeKind::kSphere:
        leaf.a = src.Vector("c"), leaf.r = src.Number("r");
        own = Box3(leaf.a - Vec3d::Constant(leaf.r), leaf.a + Vec3d::Constant(leaf.r));
        break;
      case NodeKind::kBox:
        leaf.a = src.Vector("min"), leaf.b = src.Vector("max");
        own = Box3(leaf.a, leaf.b);
        break;
      case NodeKind::kCylinder:
        leaf.a = src.Vector("a"), leaf.b = src.Vector("b"), leaf.r = src.Number("r");
        own =
            Box3(leaf.a.cwiseMin(leaf.b) - Vec3d::Constant(leaf.r), leaf.a.cwiseMax(leaf.b) + Vec3d::Constant(leaf.r));
        break;
      case NodeKind::kTorus:
        leaf.a = src.Vector("c"), leaf.axis = src.Vector("axis").normalized();
        leaf.major = src.Number("R"), leaf.r = src.Number("r");
        own = Box3(leaf.a - Vec3d::Constant(leaf.major + leaf.r), leaf.a + Vec3d::Constant(leaf.major + leaf.r));
        break;
      case NodeKind::kPlane:
        leaf.a = src.Vector("p"), leaf.axis = src.Vector("n").normalized();
        leaf.unbounded = true;
        break;
      case NodeKind::kJob: {
        auto it = job_index.find(src.job_id);
        if (it == job_index.end()) {
          auto operand = resolve(src.job_id);
          if (operand.ok() && !operand->value) operand = absl::InternalError("an operand without a value");
          if (!operand.ok()) {
            return absl::Status(operand.status().code(),
                                core::StrCat("job:", src.job_id, ": ", operand.status().message()));
          }
          it = job_index.emplace(src.job_id, static_cast<int>(jobs.size())).first;
          jobs.push_back(std::make_unique<Operand>(*std::move(operand)));
        }
        leaf.job = jobs[static_cast<size_t>(it->second)].get();
        // The cull box: the operand's box with two of its cells of margin, in world units.
        leaf.margin = 2 * leaf.job->cell_size * outer.scale;
        own = leaf.job->bounds;
        own.extend(own.min() - Vec3d::Constant(2 * leaf.job->cell_size));
        own.extend(own.max() + Vec3d::Constant(2 * leaf.job->cell_size));
        break;
      }
      default: return absl::InternalError("unexpected csg node");
    }
    if (!leaf.unbounded) {
      for (int corner = 0; corner < 8; ++corner) {
        const Vec3d y((corner & 1) ? own.max().x() : own.min().x(), (corner & 2) ? own.max().y() : own.min().y(),
                      (corner & 4) ? own.max().z() : own.min().z());
        leaf.bounds.extend(outer.ToWorld(y));
      }
    }
    leaf.cull = leaf.bounds;
    nodes[static_cast<size_t>(index)] = leaf;
    leaves.push_back(index);
    return absl::OkStatus();
  }

  // A union holds its operands' boxes, an intersection their overlap, a difference its first.
  void CombineBounds(Node& n) const {
    bool first = true;
    for (size_t k = 0; k < n.children.size(); ++k) {
      const Node& c = nodes[static_cast<size_t>(n.children[k])];
      if (n.kind == NodeKind::kDifference && k > 0) break;
      if (first) {
        n.bounds = c.bounds, n.unbounded = c.unbounded, first = false;
        continue;
      }
      if (n.kind == NodeKind::kUnion) {
        n.unbounded = n.unbounded || c.unbounded;
        n.bounds.extend(c.bounds);
      } else if (n.unbounded) {
        n.bounds = c.bounds, n.unbounded = c.unbounded;
      } else if (!c.unbounded) {
        n.bounds = n.bounds.intersection(c.bounds);
      }
    }
  }
};

CsgFunction::CsgFunction(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
CsgFunction::~CsgFunction() = default;

core::FieldValue CsgFunction::Value(const Vec3d& x) const {
  const Eval e = impl_->Evaluate(0, x, false);
  return {e.value, e.defined};
}

core::FieldGradient CsgFunction::ValueAndGradient(const Vec3d& x) const {
  const Eval e = impl_->Evaluate(0, x, true);
  return {e.value, e.gradient, e.defined};
}

core::FieldGradient CsgFunction::ValueAndGradientOnly(const Vec3d& x) const {
  const Eval e = impl_->Evaluate(0, x, true);
  return {e.value, e.gradient, std::isfinite(e.value)};
}

int CsgFunction::ActiveOperand(const Vec3d& x) const { return impl_->Evaluate(0, x, false).operand; }
int CsgFunction::operand_count() const { return static_cast<int>(impl_->leaves.size()); }
const Box3& CsgFunction::bounds() const { return impl_->bounds; }

absl::Status Validate(const CsgParams& params) {
  if (!(params.cell_size >= 0) || !std::isfinite(params.cell_size)) {
    return absl::InvalidArgumentError("cell_size must be 0 (automatic) or a positive length");
  }
  if (params.max_leaves < 1) return absl::InvalidArgumentError("max_leaves must be positive");
  return extract::Validate(params.marching);
}

absl::StatusOr<std::unique_ptr<CsgFunction>> BuildCsg(const CsgNode& root, const OperandResolver& resolve) {
  auto built = std::make_unique<CsgFunction::Impl>();
  CsgFunction::Impl& m = *built;
  absl::flat_hash_map<std::string, int> job_index;
  LSQSURF_RETURN_IF_ERROR(m.Add(root, Similarity{}, resolve, job_index));
  const CsgFunction::Impl::Node& top = m.nodes[0];
  if (top.unbounded) {
    return absl::InvalidArgumentError(
        "the csg solid is unbounded (a plane's half-space reaches infinity): intersect it with a bounded solid");
  }
  if (top.bounds.isEmpty()) return absl::InvalidArgumentError("the csg solid is empty: its operands do not overlap");
  if (!(top.bounds.sizes().maxCoeff() <= kMaxSolidExtent)) {
    return absl::InvalidArgumentError(core::StrCat("the csg solid is ", top.bounds.sizes().maxCoeff(),
                                                   " model units across; at most ", kMaxSolidExtent, " are supported"));
  }
  m.bounds = top.bounds;
  return std::make_unique<CsgFunction>(std::move(built));
}

namespace {

// Finest-level cell centres near a primitive leaf's surface: descends an octree over `root`
// and skips every cell whose centre is farther from the surface than its half-diagonal (the
// leaf value is an exact world distance, so no surface can pass there).
// The finest cells along a primitive's surface, as seeds; at most `max_seeds` in `out`, else
// kResourceExhausted (the estimate that ExtractCsg checks first can be passed by a surface that
// folds more than a convex one). Cancellation is honoured as it descends.
absl::Status PrimitiveSeeds(const CsgFunction::Impl& m, const CsgFunction::Impl::Node& leaf, const Box3& root,
                            int depth, int64_t max_seeds, std::vector<Vec3f>& out, core::JobContext& ctx) {
  struct Cell {
    Vec3d lo;
    int level;
  };
  const double edge = root.sizes().x();
  std::vector<Cell> stack{{root.min(), 0}};
  for (int64_t visited = 0; !stack.empty(); ++visited) {
    if ((visited & 0xffff) == 0) LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
    if (static_cast<int64_t>(out.size()) > max_seeds) {
      return absl::ResourceExhaustedError(core::StrCat("the csg solid's surface needs more than ", max_seeds,
                                                       " cells at this cell_size; give a larger one"));
    }
    const Cell c = stack.back();
    stack.pop_back();
    const double size = std::ldexp(edge, -c.level);
    const Vec3d centre = c.lo + Vec3d::Constant(size / 2);
    const double half_diagonal = size * std::sqrt(3.0) / 2;
    if (std::abs(m.Leaf(leaf, centre, false).value) > half_diagonal * 1.0001) continue;
    if (c.level == depth) {
      out.push_back(centre.cast<float>());
      continue;
    }
    for (int k = 0; k < 8; ++k) {
      stack.push_back(
          {c.lo + Vec3d((k & 1) ? size / 2 : 0, (k & 2) ? size / 2 : 0, (k & 4) ? size / 2 : 0), c.level + 1});
    }
  }
  return absl::OkStatus();
}

}  // namespace

// Seeds of the extraction: points near the combined surface, one per finest cell; `fine_seeds`
// those that need the finest cells.
absl::Status FindSeeds(const CsgFunction& function, const CsgFunction::Impl& m, const Box3& root, int depth,
                       double cell, int64_t max_seeds, std::vector<Vec3f>& seeds, std::vector<Vec3f>& fine_seeds,
                       core::JobContext& ctx) {
  // Candidates near each operand's own surface; `crease` marks those that need the finest cells
  // whatever the curvature, or for a job's points the leaf that decides (its creases).
  constexpr int32_t kNoCrease = -2, kCrease = -1;
  std::vector<Vec3f> candidates;
  std::vector<int32_t> crease;
  for (int index : m.leaves) {
    const auto& leaf = m.nodes[static_cast<size_t>(index)];
    if (leaf.job == nullptr) {
      LSQSURF_RETURN_IF_ERROR(PrimitiveSeeds(m, leaf, root, depth, max_seeds, candidates, ctx));
      crease.resize(candidates.size(), kNoCrease);  // Their curvature is the chord rule's.
      continue;
    }
    const int32_t decides = leaf.job->near_crease ? index : kCrease;
    for (const Vec3f& p : leaf.job->surface_points) {
      const Vec3d x = leaf.to_world.ToWorld(p.cast<double>());
      if (!m.bounds.contains(x)) continue;
      candidates.push_back(x.cast<float>());
      crease.push_back(decides);
    }
  }
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  // One candidate per finest cell, then only those near the combined surface.
  absl::flat_hash_map<std::array<int32_t, 3>, uint32_t> cells;
  std::vector<Vec3f> distinct;
  std::vector<int32_t> distinct_crease;
  for (size_t i = 0; i < candidates.size(); ++i) {
    const Vec3d g = (candidates[i].cast<double>() - root.min()) / cell;
    const std::array<int32_t, 3> key{static_cast<int32_t>(std::floor(g.x())), static_cast<int32_t>(std::floor(g.y())),
                                     static_cast<int32_t>(std::floor(g.z()))};
    auto [it, fresh] = cells.emplace(key, static_cast<uint32_t>(distinct.size()));
    if (fresh) {
      distinct.push_back(candidates[i]);
      distinct_crease.push_back(crease[i]);
    } else if (int32_t& d = distinct_crease[it->second]; d == kNoCrease || (d >= 0 && crease[i] == kCrease)) {
      d = crease[i];
    }
  }
  candidates.clear();
  cells.clear();
  // A job's own rule where one of its points came first (in its own coordinates).
  const auto needs_fine = [&](size_t i) {
    const int32_t d = distinct_crease[i];
    if (d < 0) return d == kCrease;
    const auto& leaf = m.nodes[static_cast<size_t>(d)];
    return leaf.job->near_crease(leaf.to_world.ToLocal(distinct[i].cast<double>()));
  };
  // Kept: near the combined surface. Fine: at an operand's crease, or where two operands meet (the
  // intersection curves and creases need the finest cells to be placed well; curvature is
  // decided later, on the combined surface).
  std::vector<char> state(distinct.size());  // 0 dropped, 1 coarse, 2 fine.
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      distinct.size(), 1024,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) {
          const Vec3d x = distinct[i].cast<double>();
          if (!(std::abs(function.ValueOnly(x)) <= 2 * cell)) continue;
          int near = 0;
          for (int index : m.leaves) {
            near += std::abs(m.Leaf(m.nodes[static_cast<size_t>(index)], x, false).value) <= 2 * cell;
          }
          state[i] = near >= 2 || needs_fine(i) ? 2 : 1;
        }
      },
      &ctx));
  for (size_t i = 0; i < distinct.size(); ++i) {
    if (state[i] >= 1) seeds.push_back(distinct[i]);
    if (state[i] == 2) fine_seeds.push_back(distinct[i]);
  }
  distinct.clear();
  return absl::OkStatus();
}

namespace {

// The finest cell's edge ExtractCsg uses: the given one, else the referenced jobs' finest, else
// 1/256 of the solid's longest side.
double ExtractionCell(const CsgFunction::Impl& m, const CsgParams& params) {
  double cell = params.cell_size;
  if (cell == 0) {
    cell = m.bounds.sizes().maxCoeff() / 256;
    bool from_jobs = false;
    for (int index : m.leaves) {
      const auto& leaf = m.nodes[static_cast<size_t>(index)];
      if (leaf.job == nullptr) continue;
      const double own = leaf.job->cell_size * leaf.to_world.scale;
      cell = from_jobs ? std::min(cell, own) : own;
      from_jobs = true;
    }
  }
  return cell;
}

// A primitive's surface area in its own units (planes, unbounded, count for nothing here: only
// their part inside the solid's box, which the box bound below takes).
double OwnArea(const CsgFunction::Impl::Node& n) {
  switch (n.kind) {
    case NodeKind::kSphere: return 4 * M_PI * n.r * n.r;
    case NodeKind::kBox: {
      const Vec3d s = (n.b - n.a).cwiseAbs();
      return 2 * (s.x() * s.y() + s.y() * s.z() + s.z() * s.x());
    }
    case NodeKind::kCylinder: return 2 * M_PI * n.r * ((n.b - n.a).norm() + n.r);
    case NodeKind::kTorus: return 4 * M_PI * M_PI * n.major * n.r;
    default: return std::numeric_limits<double>::infinity();
  }
}

}  // namespace

absl::StatusOr<double> EstimateSurfaceCells(const CsgFunction& function, const CsgParams& params) {
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  const CsgFunction::Impl& m = function.impl();
  const double cell = ExtractionCell(m, params);
  if (!(cell > 0)) return absl::InvalidArgumentError("the solid has no extent to size cells by");
  // A convex surface inside a box has at most the box's area there; a torus is two such sheets.
  const Vec3d box = m.bounds.sizes() + Vec3d::Constant(4 * cell);
  const double box_area = 2 * (box.x() * box.y() + box.y() * box.z() + box.z() * box.x());
  double cells = 0;
  for (int index : m.leaves) {
    const auto& leaf = m.nodes[static_cast<size_t>(index)];
    if (leaf.job != nullptr) {
      cells += static_cast<double>(leaf.job->surface_points.size());  // One seed per point at most.
      continue;
    }
    const double area = OwnArea(leaf) * leaf.to_world.scale * leaf.to_world.scale;
    // A plane crosses about √3 cells per cell² of its area.
    cells += std::sqrt(3.0) * std::min(area, (leaf.kind == NodeKind::kTorus ? 2 : 1) * box_area) / (cell * cell);
  }
  return cells;
}

absl::Status CheckExtractionSize(const CsgFunction& function, const CsgParams& params) {
  LSQSURF_ASSIGN_OR_RETURN(const double estimate, EstimateSurfaceCells(function, params));
  if (estimate > static_cast<double>(params.max_leaves)) {
    return absl::ResourceExhaustedError(core::StrCat("the csg solid's surface needs about ", std::llround(estimate),
                                                     " cells at this cell_size, more than the ", params.max_leaves,
                                                     " a csg job may use; give a larger cell_size"));
  }
  return absl::OkStatus();
}

absl::StatusOr<extract::IsosurfaceResult> ExtractCsg(const CsgFunction& function, const CsgParams& params,
                                                     core::JobContext& ctx, CsgStats* stats) {
  LSQSURF_RETURN_IF_ERROR(CheckExtractionSize(function, params));
  const CsgFunction::Impl& m = function.impl();
  const double cell = ExtractionCell(m, params);
  // The seeds' cube: the solid's box with margin, at a power-of-two multiple of the cell.
  const double extent = m.bounds.sizes().maxCoeff() + 4 * cell;
  const int depth = static_cast<int>(std::ceil(std::log2(extent / cell)));
  if (depth > extract::AdaptiveOctree::kMaxDepth) {
    return absl::InvalidArgumentError(
        core::StrCat("cell_size ", cell, " is too small for a solid of extent ", m.bounds.sizes().maxCoeff()));
  }
  const double side = std::ldexp(cell, depth);
  const Box3 root(m.bounds.center() - Vec3d::Constant(side / 2), m.bounds.center() + Vec3d::Constant(side / 2));

  ctx.ReportProgress("finding the surface", 0.0);
  std::vector<Vec3f> seeds, fine_seeds;
  LSQSURF_RETURN_IF_ERROR(FindSeeds(function, m, root, depth, cell, params.max_leaves, seeds, fine_seeds, ctx));
  if (stats != nullptr) stats->seeds = static_cast<int64_t>(seeds.size()), stats->cell_size = cell;
  if (seeds.empty()) return absl::FailedPreconditionError("the csg solid is empty: no surface passes its box");
  // The tree: three levels coarser than the cell along the whole surface, split towards the cell
  // where the combined surface curves (chord_error), along intersection curves and creases, 2:1
  // balanced.
  const int band_level = std::max(1, depth - 3);
  extract::AdaptiveOctree tree(root, depth);
  extract::SurfaceBand band = extract::MarkSurfaceBand(tree, seeds, band_level);
  const extract::SurfaceBand near_data = extract::MarkSurfaceBand(tree, seeds, depth);
  const extract::SurfaceBand forced = extract::MarkSurfaceBand(tree, fine_seeds, depth);
  const double chord_bound = params.chord_error * core::Diagonal(m.bounds);
  LSQSURF_RETURN_IF_ERROR(extract::RefineSurfaceBand(
      tree, band, band_level, near_data,
      [&](const extract::OctreeCell& c) {
        return forced.ancestors.contains(extract::CellKey(c)) ||
               extract::EstimateChordError(function, tree.CellCentre(c), tree.CellEdge(c.level)) > chord_bound;
      },
      ctx));
  tree.Balance();
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  band = {};
  // Extraction starts at the finest cells of the seeds (it maps them to the leaves holding them).
  absl::flat_hash_set<uint64_t> start_keys;
  for (const Vec3f& p : seeds) start_keys.insert(extract::CellKey(tree.CellAt(depth, p.cast<double>())));
  std::vector<extract::OctreeCell> start;
  start.reserve(start_keys.size());
  for (uint64_t key : start_keys) start.push_back(extract::CellFromKey(key));
  core::SubContext extract_ctx(ctx, "extracting surface", 0.05, 0.97);
  auto result =
      extract::ExtractIsosurfaceOnTree(function, tree, start, params.max_leaves, params.marching, extract_ctx);
  if (!result.ok()) return result;
  core::TriangleMesh& mesh = result->mesh;
  if (mesh.faces.empty()) return absl::FailedPreconditionError("the csg solid is empty: no surface was found");
  core::ScalarAttribute operand{"operand", std::vector<float>(mesh.vertices.size())};
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      mesh.vertices.size(), 1024,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) {
          operand.values[i] = static_cast<float>(function.ActiveOperand(mesh.vertices[i].cast<double>()));
        }
      },
      &ctx));
  mesh.vertex_attributes.push_back(std::move(operand));
  return result;
}

}  // namespace lsqsurf::csg
