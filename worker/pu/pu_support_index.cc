#include <algorithm>
#include <mutex>

#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/pu/pu_internal.h"

namespace lsqsurf::pu {
namespace {

// Whether a fit's support meets a node's cube: the one test behind the influence lists.
bool SupportMeetsCube(const PuFunction::Impl& impl, const LocalFit& fit, const Node& n) {
  const Vec3d lo = impl.origin + Vec3d(n.x, n.y, n.z) * impl.Edge(n.level);
  const Vec3d hi = lo + Vec3d::Constant(impl.Edge(n.level));
  const Vec3d nearest = fit.centre.cwiseMax(lo).cwiseMin(hi);
  return (nearest - fit.centre).squaredNorm() < fit.support_radius * fit.support_radius;
}

// Calls emit(leaf) for every leaf of the tree whose cube the fit's support meets.
template <typename Emit>
void ForEachLeafInSupport(const PuFunction::Impl& impl, const LocalFit& fit, Emit&& emit) {
  std::vector<int32_t> stack{0};
  while (!stack.empty()) {
    const int32_t id = stack.back();
    const Node& n = impl.nodes[static_cast<size_t>(id)];
    stack.pop_back();
    if (!SupportMeetsCube(impl, fit, n)) continue;
    if (n.first_child < 0) {
      emit(id);
    } else {
      for (int k = 0; k < 8; ++k) stack.push_back(n.first_child + k);
    }
  }
}

// Leaf → fits whose support meets it, so that an evaluation visits one short list.
}  // namespace

absl::Status IndexInfluence(PuFunction::Impl& impl, core::JobContext& ctx) {
  std::vector<uint32_t> leaf_counts(impl.nodes.size() + 1, 0);
  std::vector<std::vector<std::pair<uint32_t, uint32_t>>> pairs_per_chunk;
  std::mutex chunks_mutex;
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      impl.fits.size(), 256,
      [&](size_t b, size_t e) {
        std::vector<std::pair<uint32_t, uint32_t>> pairs;
        for (size_t f = b; f < e; ++f) {
          ForEachLeafInSupport(impl, impl.fits[f], [&](int32_t leaf) {
            pairs.emplace_back(static_cast<uint32_t>(leaf), static_cast<uint32_t>(f));
          });
        }
        std::lock_guard lock(chunks_mutex);
        pairs_per_chunk.push_back(std::move(pairs));
      },
      &ctx));
  for (const auto& chunk : pairs_per_chunk) {
    for (const auto& [leaf, fit] : chunk) ++leaf_counts[leaf + 1];
  }
  for (size_t i = 1; i < leaf_counts.size(); ++i) leaf_counts[i] += leaf_counts[i - 1];
  impl.influence_offsets = leaf_counts;
  impl.influence.resize(leaf_counts.back());
  for (const auto& chunk : pairs_per_chunk) {
    for (const auto& [leaf, fit] : chunk) impl.influence[leaf_counts[leaf]++] = fit;
  }
  // In fit order, so that sums (and a rebuilt index) do not depend on the threads' timing.
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      impl.nodes.size(), 4096,
      [&](size_t b, size_t e) {
        for (size_t leaf = b; leaf < e; ++leaf) {
          std::sort(impl.influence.begin() + impl.influence_offsets[leaf],
                    impl.influence.begin() + impl.influence_offsets[leaf + 1]);
        }
      },
      &ctx));
  return absl::OkStatus();
}

// IndexInfluence for an edit, without visiting every fit again. `after` is `before` with the
// fits of the `touched` leaves replaced by `new_fits` (indices in `after`; a touched leaf may
// have been split) and the fits renumbered by `renumber` (before's index → after's; empty when
// unchanged). An unchanged fit meets the same cubes as before, so only the leaves that a
// replaced or a new support meets, and the leaves new to the tree, get their lists rebuilt; the
// rest are renumbered. The result equals IndexInfluence(after) entry for entry.
absl::Status UpdateInfluence(const PuFunction::Impl& before, PuFunction::Impl& after, std::span<const int32_t> touched,
                             std::span<const int32_t> new_fits, std::span<const int32_t> renumber,
                             core::JobContext& ctx) {
  const size_t old_nodes = before.nodes.size(), nodes = after.nodes.size();
  auto is_leaf = [&](size_t node) { return after.nodes[node].first_child < 0; };
  auto to_after = [&](uint32_t fit) { return renumber.empty() ? static_cast<int32_t>(fit) : renumber[fit]; };
  std::vector<char> replaced(before.fits.size(), 0);
  for (int32_t t : touched) replaced[static_cast<size_t>(before.nodes[static_cast<size_t>(t)].fit)] = 1;
  // Rebuilt lists: rebuilt[slot[leaf]]; `source[leaf]`, the before-leaf whose list it starts from.
  std::vector<int32_t> slot(nodes, -1), source(nodes, -1);
  std::vector<int32_t> rebuilt_leaves;
  auto mark = [&](int32_t leaf, int32_t from) {
    if (slot[static_cast<size_t>(leaf)] >= 0) return;
    slot[static_cast<size_t>(leaf)] = static_cast<int32_t>(rebuilt_leaves.size());
    source[static_cast<size_t>(leaf)] = from;
    rebuilt_leaves.push_back(leaf);
  };
  for (int32_t t : touched) {  // Leaves new to the tree start from the split leaf's list.
    std::vector<int32_t> stack{t};
    while (!stack.empty()) {
      const int32_t id = stack.back();
      stack.pop_back();
      const Node& n = after.nodes[static_cast<size_t>(id)];
      if (n.first_child < 0) {
        mark(id, t);
      } else {
        for (int32_t k = 0; k < 8; ++k) stack.push_back(n.first_child + k);
      }
    }
  }
  for (int32_t t : touched) {
    ForEachLeafInSupport(before, before.fits[static_cast<size_t>(before.nodes[static_cast<size_t>(t)].fit)],
                         [&](int32_t leaf) {
                           if (is_leaf(static_cast<size_t>(leaf))) mark(leaf, leaf);
                         });
  }
  std::vector<std::pair<int32_t, int32_t>> added;  // (leaf, new fit)
  for (int32_t f : new_fits) {
    ForEachLeafInSupport(after, after.fits[static_cast<size_t>(f)], [&](int32_t leaf) {
      mark(leaf, leaf);  // A leaf new to the tree is marked already, from its split leaf.
      added.emplace_back(leaf, f);
    });
  }
  std::vector<std::vector<uint32_t>> rebuilt(rebuilt_leaves.size());
  for (size_t i = 0; i < rebuilt_leaves.size(); ++i) {
    const auto leaf = static_cast<size_t>(rebuilt_leaves[i]);
    const int32_t from = source[leaf];
    const bool new_leaf = leaf >= old_nodes;
    for (uint32_t k = before.influence_offsets[static_cast<size_t>(from)];
         k < before.influence_offsets[static_cast<size_t>(from) + 1]; ++k) {
      const uint32_t fit = before.influence[k];
      if (replaced[fit]) continue;
      const int32_t now = to_after(fit);
      if (new_leaf && !SupportMeetsCube(after, after.fits[static_cast<size_t>(now)], after.nodes[leaf])) continue;
      rebuilt[i].push_back(static_cast<uint32_t>(now));
    }
  }
  for (const auto& [leaf, fit] : added)
    rebuilt[static_cast<size_t>(slot[static_cast<size_t>(leaf)])].push_back(static_cast<uint32_t>(fit));
  for (std::vector<uint32_t>& list : rebuilt) std::sort(list.begin(), list.end());
  std::vector<uint32_t>& offsets = after.influence_offsets;
  offsets.assign(nodes + 1, 0);
  for (size_t node = 0; node < nodes; ++node) {
    uint32_t count = 0;
    if (slot[node] >= 0) {
      count = static_cast<uint32_t>(rebuilt[static_cast<size_t>(slot[node])].size());
    } else if (node < old_nodes && is_leaf(node)) {
      count = before.influence_offsets[node + 1] - before.influence_offsets[node];
    }
    offsets[node + 1] = offsets[node] + count;
  }
  after.influence.resize(offsets.back());
  return core::ParallelFor(
      nodes, 4096,
      [&](size_t b, size_t e) {
        for (size_t node = b; node < e; ++node) {
          uint32_t* out = after.influence.data() + offsets[node];
          if (slot[node] >= 0) {
            const std::vector<uint32_t>& list = rebuilt[static_cast<size_t>(slot[node])];
            std::copy(list.begin(), list.end(), out);
          } else if (offsets[node + 1] > offsets[node]) {
            for (uint32_t k = before.influence_offsets[node]; k < before.influence_offsets[node + 1]; ++k) {
              *out++ = static_cast<uint32_t>(to_after(before.influence[k]));
            }
          }
        }
      },
      &ctx);
}

}  // namespace lsqsurf::pu
