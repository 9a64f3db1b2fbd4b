#include <algorithm>
#include <cmath>

#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/pu/pu_internal.h"

namespace lsqsurf::pu {

namespace {

// Drops the fits no leaf refers to, keeping the others in their order (so that the support
// lists of untouched leaves, sorted by index, sum in the same order as before). Returns the
// renumbering (old index → new, −1 for a dropped fit), empty when no fit is dropped.
std::vector<int32_t> CompactFits(PuFunction::Impl& m) {
  std::vector<int32_t> new_index(m.fits.size(), -1);
  for (const Node& n : m.nodes) {
    if (n.fit >= 0 && n.first_child < 0) new_index[static_cast<size_t>(n.fit)] = 0;
  }
  if (std::find(new_index.begin(), new_index.end(), -1) == new_index.end()) return {};
  std::vector<LocalFit> kept;
  for (size_t f = 0; f < m.fits.size(); ++f) {
    if (new_index[f] < 0) continue;
    new_index[f] = static_cast<int32_t>(kept.size());
    kept.push_back(m.fits[f]);
  }
  for (Node& n : m.nodes) {
    if (n.fit >= 0) n.fit = n.first_child < 0 ? new_index[static_cast<size_t>(n.fit)] : -1;
  }
  m.fits = std::move(kept);
  return new_index;
}

// The indices of the points inside a node's cube (the split rule's half-open octants).
void PointsInCube(const PuFunction::Impl& m, const Node& n, std::vector<core::Neighbor>& scratch,
                  std::vector<uint32_t>& out) {
  const double edge = m.Edge(n.level);
  const Vec3d lo = m.origin + Vec3d(n.x, n.y, n.z) * edge, hi = lo + Vec3d::Constant(edge);
  m.cloud->kd_tree->Radius(((lo + hi) / 2).cast<float>(), static_cast<float>(edge * kSqrt3 / 2 * 1.001), scratch);
  for (const core::Neighbor& p : scratch) {
    const Vec3d x = m.cloud->positions[p.index].cast<double>();
    if ((x.array() >= lo.array()).all() && (x.array() < hi.array()).all()) out.push_back(p.index);
  }
}

// A remove edit's points: those outside the ball, with a point index of their own. The fits
// centred in the ball go; coverage changes where a removed point was the nearest, or one the
// rim test read.
absl::Status RemovePoints(const PuFunction::Impl& b, PuFunction::Impl& m, const PuEdit& edit,
                          std::span<const int32_t> touched, PuEditStats& local) {
  m.cloud = std::make_shared<PointData>();
  const double r2 = edit.radius * edit.radius;
  double removed_spacing = 0;
  for (size_t i = 0; i < b.cloud->positions.size(); ++i) {
    if ((b.cloud->positions[i].cast<double>() - edit.centre).squaredNorm() < r2) {
      ++local.points_removed;
      if (!b.cloud->local_spacing.empty())
        removed_spacing = std::max<double>(removed_spacing, b.cloud->local_spacing[i]);
      continue;
    }
    m.cloud->positions.push_back(b.cloud->positions[i]);
    m.cloud->normals.push_back(b.cloud->normals[i]);
    if (!b.cloud->local_spacing.empty()) m.cloud->local_spacing.push_back(b.cloud->local_spacing[i]);
  }
  if (m.cloud->positions.size() < 4) return absl::FailedPreconditionError("the ball holds nearly every point");
  if (m.coverage_check)
    local.changed.push_back({edit.centre, edit.radius + kRimReadFactor * m.coverage_factor * removed_spacing});
  for (int32_t node : touched) {
    Node& n = m.nodes[static_cast<size_t>(node)];
    if ((m.fits[static_cast<size_t>(n.fit)].centre - edit.centre).norm() < edit.radius) n.fit = -1;
  }
  m.cloud->kd_tree = std::make_unique<core::KdTree>(m.cloud->positions);
  return absl::OkStatus();
}

}  // namespace

const core::ParamTable<PuEdit>& PuEditParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PuEdit>();
    for (int axis = 0; axis < 3; ++axis) {
      const std::string name = std::string("center_") + "xyz"[axis];
      t->Custom(
          {.name = name,
           .type = core::ParamType::kReal,
           .min_value = -1e12,
           .max_value = 1e12,
           .unit = "model units",
           .help = std::string(1, "xyz"[axis]) + " of the ball's centre"},
          [axis](const PuEdit& e) { return e.centre[axis]; }, [axis](PuEdit& e, double v) { e.centre[axis] = v; });
    }
    t->Real<&PuEdit::radius>("radius", 0, 1e12, "model units", "the ball's radius (required, more than 0)")
        .Choice<&PuEdit::action>(
            "action",
            {{"set_degree", static_cast<int>(PuEditAction::kSetDegree),
              "refit the local fits meeting the ball at `degree`"},
             {"refit", static_cast<int>(PuEditAction::kRefit), "grow their cells again under `error_threshold`"},
             {"remove", static_cast<int>(PuEditAction::kRemove),
              "drop the points in the ball and the fits centred there (a hole)"}},
            "what the edit does")
        .Integer<&PuEdit::degree>("degree", 0, kMaxDegree, "", "set_degree: the polynomial degree")
        .Real<&PuEdit::error_threshold>("error_threshold", 1e-6, 0.1, "share of the diagonal",
                                        "refit: the largest Taubin distance accepted")
        .AddRule([](const PuEdit& e) {
          return e.radius > 0 ? absl::OkStatus() : absl::InvalidArgumentError("give the ball's radius (radius > 0)");
        });
    return t;
  }();
  return *table;
}

absl::Status Validate(const PuEdit& edit) { return PuEditParamTable().Validate(edit); }

absl::StatusOr<std::unique_ptr<PuFunction>> EditPu(const PuFunction& base, const PuEdit& edit, core::JobContext& ctx,
                                                   PuEditStats* stats) {
  LSQSURF_RETURN_IF_ERROR(Validate(edit));
  const PuFunction::Impl& b = base.impl();
  auto edited = std::make_unique<PuFunction::Impl>();
  PuFunction::Impl& m = *edited;
  m.stats = b.stats;
  m.params = b.params, m.origin = b.origin, m.root_edge = b.root_edge, m.deepest_level = b.deepest_level;
  m.coverage_check = b.coverage_check, m.coverage_factor = b.coverage_factor;
  m.nodes = b.nodes, m.fits = b.fits, m.sharp_fits = b.sharp_fits;
  PuEditStats local;
  // The leaves whose fit's support meets the ball.
  std::vector<int32_t> touched;
  for (size_t i = 0; i < m.nodes.size(); ++i) {
    const Node& n = m.nodes[i];
    if (n.first_child >= 0 || n.fit < 0) continue;
    const LocalFit& f = m.fits[static_cast<size_t>(n.fit)];
    const double gap = (f.centre - edit.centre).norm();
    if (gap >= f.support_radius + edit.radius) continue;
    touched.push_back(static_cast<int32_t>(i));
    local.reach = std::max(local.reach, gap + f.support_radius);
    local.changed.push_back({f.centre, f.support_radius});
  }
  if (touched.empty()) return absl::FailedPreconditionError("no local fit meets the ball: nothing to edit there");
  local.fits_replaced = static_cast<int64_t>(touched.size());
  if (edit.action == PuEditAction::kRemove) {
    LSQSURF_RETURN_IF_ERROR(RemovePoints(b, m, edit, touched, local));
  } else {
    m.cloud = b.cloud;
  }
  const double diagonal = core::Diagonal(core::BoundingBox(m.cloud->positions));
  PuParams params = m.params;
  params.sharp = false;  // An edited region is made smooth; its creases stay where they were fitted.
  double bound = params.error_threshold * diagonal;
  if (edit.action == PuEditAction::kSetDegree) {
    params.max_degree = edit.degree;
    params.max_depth = 0;  // No cell splits: each keeps its place in the tree.
    bound = 0;             // The highest degree the points determine, up to `degree`.
  } else if (edit.action == PuEditAction::kRefit) {
    params.error_threshold = edit.error_threshold;
    bound = edit.error_threshold * diagonal;
  }
  const BuildContext bc(params, m, m.cloud->normals, bound);
  if (edit.action == PuEditAction::kSetDegree) {
    std::vector<CellOutcome> outcomes(touched.size());
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        touched.size(), 8,
        [&](size_t begin, size_t end) {
          thread_local Scratch scratch;
          for (size_t i = begin; i < end; ++i) {
            outcomes[i] = ProcessCell(bc, m.nodes[static_cast<size_t>(touched[i])], {}, 0, scratch);
          }
        },
        &ctx));
    for (size_t i = 0; i < touched.size(); ++i) {
      Node& n = m.nodes[static_cast<size_t>(touched[i])];
      if (!outcomes[i].has_fit) {
        n.fit = -1;
        continue;
      }
      outcomes[i].fit.sharp = -1;
      outcomes[i].fit.feature = Feature::kSmooth;
      m.fits[static_cast<size_t>(n.fit)] = outcomes[i].fit;
    }
  } else if (edit.action == PuEditAction::kRefit) {
    std::vector<uint32_t> order;
    std::vector<std::array<uint32_t, 2>> ranges(m.nodes.size(), {0, 0});
    std::vector<core::Neighbor> scratch;
    for (int32_t node : touched) {
      Node& n = m.nodes[static_cast<size_t>(node)];
      n.fit = -1;
      const auto begin = static_cast<uint32_t>(order.size());
      PointsInCube(m, n, scratch, order);
      ranges[static_cast<size_t>(node)] = {begin, static_cast<uint32_t>(order.size())};
    }
    PuStats grown;
    grown.leaves_per_depth.assign(static_cast<size_t>(params.max_depth) + 1, 0);
    grown.fits_per_depth.assign(static_cast<size_t>(params.max_depth) + 1, 0);
    LSQSURF_RETURN_IF_ERROR(GrowSubtrees(bc, m, order, ranges, touched, params.max_depth, grown, ctx));
  }
  const std::vector<int32_t> renumber = CompactFits(m);
  if (m.fits.empty()) return absl::FailedPreconditionError("the edit leaves no local fit");
  // The new fits' supports (a refit's may reach past the ones they replace).
  std::vector<int32_t> new_fits;
  std::vector<int32_t> stack(touched.begin(), touched.end());
  while (!stack.empty()) {
    const Node& n = m.nodes[static_cast<size_t>(stack.back())];
    stack.pop_back();
    if (n.first_child >= 0) {
      for (int32_t c = 0; c < 8; ++c) stack.push_back(n.first_child + c);
    } else if (n.fit >= 0) {
      const LocalFit& f = m.fits[static_cast<size_t>(n.fit)];
      new_fits.push_back(n.fit);
      local.changed.push_back({f.centre, f.support_radius});
      local.reach = std::max(local.reach, (f.centre - edit.centre).norm() + f.support_radius);
    }
  }
  LSQSURF_RETURN_IF_ERROR(UpdateInfluence(b, m, touched, new_fits, renumber, ctx));
  local.fits_after = static_cast<int64_t>(m.fits.size());
  if (stats != nullptr) *stats = local;
  return std::make_unique<PuFunction>(std::move(edited));
}

}  // namespace lsqsurf::pu
