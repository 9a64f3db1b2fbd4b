// J1a: Castelo et al. 2006; construction of METHODS.md §1.3 (see j1a.h).
#include "worker/extract/j1a.h"

#include <algorithm>
#include <cassert>

namespace lsqsurf::extract {

VertexKey PackVertex(uint32_t x, uint32_t y, uint32_t z) {
  return (static_cast<uint64_t>(x) << 42) | (static_cast<uint64_t>(y) << 21) | z;
}

std::array<uint32_t, 3> UnpackVertex(VertexKey key) {
  constexpr uint64_t mask = (uint64_t{1} << 21) - 1;
  return {static_cast<uint32_t>((key >> 42) & mask), static_cast<uint32_t>((key >> 21) & mask),
          static_cast<uint32_t>(key & mask)};
}

AdaptiveOctree::AdaptiveOctree(const Box3& root, int max_depth) : max_depth_(std::clamp(max_depth, 0, kMaxDepth)) {
  origin_ = root.min();
  const double size = std::max(root.sizes().maxCoeff(), 1e-30);
  unit_ = size / static_cast<double>(CellUnits(0));
  cells_[CellKey({})] = true;
  leaves_[CellKey({})] = OctreeCell{};
}

uint64_t CellKey(const OctreeCell& c) {
  return (static_cast<uint64_t>(c.level) << 60) | (static_cast<uint64_t>(c.x) << 40) |
         (static_cast<uint64_t>(c.y) << 20) | c.z;
}

OctreeCell CellFromKey(uint64_t key) {
  constexpr uint64_t mask = 0xfffff;
  return {static_cast<int>(key >> 60), static_cast<uint32_t>((key >> 40) & mask),
          static_cast<uint32_t>((key >> 20) & mask), static_cast<uint32_t>(key & mask)};
}

bool AdaptiveOctree::InRange(int level, int64_t x, int64_t y, int64_t z) const {
  const int64_t n = int64_t{1} << level;
  return x >= 0 && y >= 0 && z >= 0 && x < n && y < n && z < n;
}

bool AdaptiveOctree::IsLeaf(const OctreeCell& c) const {
  auto it = cells_.find(CellKey(c));
  return it != cells_.end() && it->second;
}

bool AdaptiveOctree::IsSubdivided(const OctreeCell& c) const {
  auto it = cells_.find(CellKey(c));
  return it != cells_.end() && !it->second;
}

const OctreeCell* AdaptiveOctree::LeafContaining(const OctreeCell& c) const {
  // Children are made eight at a time, so the first cell that exists on the way up is the leaf
  // holding `c`, or `c` itself subdivided (then no leaf holds it: return at once, not at the root).
  for (int l = c.level; l >= 0; --l) {
    const int shift = c.level - l;
    const uint64_t key = CellKey({l, c.x >> shift, c.y >> shift, c.z >> shift});
    const auto it = cells_.find(key);
    if (it == cells_.end()) continue;
    return it->second ? &leaves_.find(key)->second : nullptr;
  }
  return nullptr;
}

void AdaptiveOctree::Split(const OctreeCell& leaf) {
  if (leaf.level >= max_depth_ || !IsLeaf(leaf)) return;
  cells_[CellKey(leaf)] = false;
  leaves_.erase(CellKey(leaf));
  for (uint32_t i = 0; i < 8; ++i) {
    const OctreeCell child{leaf.level + 1, 2 * leaf.x + (i & 1), 2 * leaf.y + ((i >> 1) & 1),
                           2 * leaf.z + ((i >> 2) & 1)};
    cells_[CellKey(child)] = true;
    leaves_[CellKey(child)] = child;
  }
}

void AdaptiveOctree::Refine(const std::function<bool(const OctreeCell&)>& refine) {
  std::vector<OctreeCell> work = Leaves();
  while (!work.empty()) {
    const OctreeCell c = work.back();
    work.pop_back();
    if (c.level >= max_depth_ || !IsLeaf(c) || !refine(c)) continue;
    Split(c);
    for (uint32_t i = 0; i < 8; ++i) {
      work.push_back({c.level + 1, 2 * c.x + (i & 1), 2 * c.y + ((i >> 1) & 1), 2 * c.z + ((i >> 2) & 1)});
    }
  }
}

void AdaptiveOctree::Balance() {
  // Finest leaves first: a split can only create finer leaves, which are then re-examined.
  std::vector<OctreeCell> work = Leaves();
  std::sort(work.begin(), work.end(), [](const OctreeCell& a, const OctreeCell& b) { return a.level < b.level; });
  while (!work.empty()) {
    const OctreeCell c = work.back();
    work.pop_back();
    if (c.level < 2 || !IsLeaf(c)) continue;
    // The 26 neighbours of `c` lie in the 2×2×2 block of cells one level up that holds its
    // parent: a neighbour's leaf is too coarse exactly where that block's cell does not exist.
    const int up = c.level - 1;
    const std::array<uint32_t, 3> parent = {c.x >> 1, c.y >> 1, c.z >> 1};
    const std::array<uint32_t, 3> odd = {c.x & 1, c.y & 1, c.z & 1};
    for (uint32_t corner = 1; corner < 8; ++corner) {
      std::array<int64_t, 3> q{};
      for (int axis = 0; axis < 3; ++axis) {
        const int64_t step = (corner >> axis) & 1 ? (odd[axis] ? 1 : -1) : 0;
        q[axis] = int64_t{parent[axis]} + step;
      }
      if (!InRange(up, q[0], q[1], q[2])) continue;
      const OctreeCell block{up, static_cast<uint32_t>(q[0]), static_cast<uint32_t>(q[1]), static_cast<uint32_t>(q[2])};
      if (cells_.contains(CellKey(block))) continue;
      const OctreeCell* n = LeafContaining(block);
      if (n == nullptr) continue;
      const OctreeCell coarse = *n;
      Split(coarse);
      for (uint32_t i = 0; i < 8; ++i) {
        work.push_back(
            {coarse.level + 1, 2 * coarse.x + (i & 1), 2 * coarse.y + ((i >> 1) & 1), 2 * coarse.z + ((i >> 2) & 1)});
      }
      work.push_back(c);  // Its other neighbours may still be too coarse.
    }
  }
}

std::vector<OctreeCell> AdaptiveOctree::Leaves() const {
  std::vector<OctreeCell> out;
  out.reserve(leaves_.size());
  for (const auto& [key, cell] : leaves_) out.push_back(cell);
  std::sort(out.begin(), out.end(), [](const OctreeCell& a, const OctreeCell& b) { return CellKey(a) < CellKey(b); });
  return out;
}

OctreeCell AdaptiveOctree::CellAt(int level, const Vec3d& p) const {
  const int64_t n = int64_t{1} << level;
  const Vec3d g = (p - origin_) / CellEdge(level);
  const auto index = [&](double v) {
    return static_cast<uint32_t>(std::clamp<int64_t>(static_cast<int64_t>(std::floor(v)), 0, n - 1));
  };
  return {level, index(g.x()), index(g.y()), index(g.z())};
}

Vec3d AdaptiveOctree::Position(VertexKey key) const {
  const auto [x, y, z] = UnpackVertex(key);
  return origin_ + unit_ * Vec3d(x, y, z);
}

void AppendJ1aTetrahedra(const AdaptiveOctree& tree, const OctreeCell& leaf, std::vector<TetKeys>& out) {
  const int L = leaf.level;
  const int64_t s = tree.CellUnits(L);
  const std::array<int64_t, 3> cell = {leaf.x, leaf.y, leaf.z};
  const std::array<int64_t, 3> c0 = {cell[0] * s, cell[1] * s, cell[2] * s};
  const int64_t cells_per_axis = int64_t{1} << L;
  // Is the same-level cell at `index` subdivided (so finer leaves touch what it borders)?
  auto subdivided = [&](const std::array<int64_t, 3>& index) {
    for (int64_t v : index) {
      if (v < 0 || v >= cells_per_axis) return false;
    }
    return tree.IsSubdivided(
        {L, static_cast<uint32_t>(index[0]), static_cast<uint32_t>(index[1]), static_cast<uint32_t>(index[2])});
  };
  auto key = [](const std::array<int64_t, 3>& p) {
    return PackVertex(static_cast<uint32_t>(p[0]), static_cast<uint32_t>(p[1]), static_cast<uint32_t>(p[2]));
  };
  const std::array<int64_t, 3> centre = {c0[0] + s / 2, c0[1] + s / 2, c0[2] + s / 2};
  auto emit = [&](const std::array<int64_t, 3>& p, const std::array<int64_t, 3>& q, const std::array<int64_t, 3>& v) {
    TetKeys t = {key(centre), key(p), key(q), key(v)};
    // Orientation from integer coordinates: exact.
    int64_t m[3][3];
    for (int r = 0; r < 3; ++r) {
      const auto& w = r == 0 ? p : r == 1 ? q : v;
      for (int k = 0; k < 3; ++k) m[r][k] = w[static_cast<size_t>(k)] - centre[static_cast<size_t>(k)];
    }
    const int64_t det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
                        m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
                        m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    assert(det != 0);
    if (det < 0) std::swap(t[2], t[3]);
    out.push_back(t);
  };
  for (int a = 0; a < 3; ++a) {
    const int b = (a + 1) % 3, c = (a + 2) % 3;
    for (int side = 0; side < 2; ++side) {
      const int64_t plane = c0[static_cast<size_t>(a)] + side * s;
      std::array<int64_t, 3> across = cell;
      across[static_cast<size_t>(a)] += side == 0 ? -1 : 1;
      const bool face_split = subdivided(across);
      const int64_t piece = face_split ? s / 2 : s;
      for (int64_t ob = 0; ob < s; ob += piece) {
        for (int64_t oc = 0; oc < s; oc += piece) {
          std::array<int64_t, 3> pc{};  // Face-piece centre.
          pc[static_cast<size_t>(a)] = plane;
          pc[static_cast<size_t>(b)] = c0[static_cast<size_t>(b)] + ob + piece / 2;
          pc[static_cast<size_t>(c)] = c0[static_cast<size_t>(c)] + oc + piece / 2;
          // The 4 edges of the piece: along `e`, at offset `f_off` (0 or piece) on axis `f`.
          for (int which = 0; which < 4; ++which) {
            const int e = which < 2 ? b : c, f = which < 2 ? c : b;
            const int64_t e_start = c0[static_cast<size_t>(e)] + (e == b ? ob : oc);
            const int64_t f_pos = c0[static_cast<size_t>(f)] + (f == b ? ob : oc) + (which % 2) * piece;
            // A whole edge of the leaf is split when a same-level cell around it is subdivided;
            // pieces of a split face are never split again in a balanced tree.
            bool edge_split = false;
            if (!face_split) {
              for (int da = -1; da <= 0 && !edge_split; ++da)
                for (int df = -1; df <= 0 && !edge_split; ++df) {
                  std::array<int64_t, 3> around{};
                  around[static_cast<size_t>(a)] = plane / s + da;
                  around[static_cast<size_t>(f)] = f_pos / s + df;
                  around[static_cast<size_t>(e)] = cell[static_cast<size_t>(e)];
                  edge_split = subdivided(around);
                }
            }
            const int64_t sub = edge_split ? piece / 2 : piece;
            for (int64_t oe = 0; oe < piece; oe += sub) {
              std::array<int64_t, 3> q = pc, v0 = pc, v1 = pc;
              q[static_cast<size_t>(f)] = v0[static_cast<size_t>(f)] = v1[static_cast<size_t>(f)] = f_pos;
              q[static_cast<size_t>(e)] = e_start + oe + sub / 2;
              v0[static_cast<size_t>(e)] = e_start + oe;
              v1[static_cast<size_t>(e)] = e_start + oe + sub;
              emit(pc, q, v0);
              emit(pc, q, v1);
            }
          }
        }
      }
    }
  }
}

}  // namespace lsqsurf::extract
