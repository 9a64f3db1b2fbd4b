// worker/extract/j1a.h — adaptive octree and its J1a tetrahedralization.
//
// Castelo, Nonato, Siqueira, Minghim, Tavares, "The J1a triangulation: an adaptive
// triangulation in any dimension", Computers & Graphics 30(5), 2006; the construction used here
// is the recursive face-centre rule of METHODS.md §1.3. Every leaf cube is cut into tetrahedra
// (cube centre, face-piece centre, edge-piece centre, corner): a face or edge of a leaf is split
// into halves where a finer leaf touches it. The predicate is a property of the face itself, so
// the two leaves that share a face triangulate it identically and the result is conforming.
// On a uniform region every leaf gets the 48 tetrahedra of Todd's J1.
//
// Vertices are named by integer coordinates at twice the finest resolution (cell centres are
// then integers too), packed 21 bits per axis into a 64-bit key: the same point is the same key
// whichever leaf produced it, which is what lets values and gradients be cached per vertex.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "worker/core/geometry.h"

namespace lsqsurf::extract {

// The core vocabulary, used throughout extraction.
using core::Box3;
using core::Triangle;
using core::TriangleMesh;
using core::Vec3d;
using core::Vec3f;

// A cube of the tree: `level` 0 is the root; x, y, z index the cube among the 2^level per axis.
struct OctreeCell {
  int level = 0;
  uint32_t x = 0, y = 0, z = 0;
  bool operator==(const OctreeCell&) const = default;
};

using VertexKey = uint64_t;

// A unique 64-bit name of a cell (level and coordinates), for hash sets and maps.
uint64_t CellKey(const OctreeCell& c);
OctreeCell CellFromKey(uint64_t key);

class AdaptiveOctree {
 public:
  static constexpr int kMaxDepth = 19;  // Keeps doubled finest coordinates within 21 bits.

  // `root` is made cubic (its largest side); `max_depth` in [0, kMaxDepth].
  AdaptiveOctree(const Box3& root, int max_depth);

  int max_depth() const { return max_depth_; }
  // Repeatedly splits every leaf for which `refine` returns true, down to max_depth.
  void Refine(const std::function<bool(const OctreeCell&)>& refine);
  // Splits a leaf into its 8 children; no-op for non-leaves and cells at max_depth.
  void Split(const OctreeCell& leaf);
  // Splits leaves until any two leaves that touch (by face, edge or corner) differ by at most
  // one level.
  void Balance();

  std::vector<OctreeCell> Leaves() const;
  bool IsLeaf(const OctreeCell& c) const;
  // True when the cell exists in the tree and has children.
  bool IsSubdivided(const OctreeCell& c) const;
  // The leaf at `c` or above it (an ancestor); nullptr when `c` is subdivided or outside.
  const OctreeCell* LeafContaining(const OctreeCell& c) const;

  // Edge length of a cell of `level`, in vertex units (twice the finest resolution).
  uint32_t CellUnits(int level) const { return 2u << (max_depth_ - level); }
  // Edge length of a cell of `level`, in model units.
  double CellEdge(int level) const { return unit_ * CellUnits(level); }
  Vec3d CellCentre(const OctreeCell& c) const {
    return origin_ + CellEdge(c.level) * Vec3d(c.x + 0.5, c.y + 0.5, c.z + 0.5);
  }
  // The cell of `level` holding `p`; points outside the root go to the nearest cell on its border.
  OctreeCell CellAt(int level, const Vec3d& p) const;
  // The model-space position of a vertex key.
  Vec3d Position(VertexKey key) const;
  const Vec3d& origin() const { return origin_; }

 private:
  bool InRange(int level, int64_t x, int64_t y, int64_t z) const;

  Vec3d origin_;
  double unit_ = 1;
  int max_depth_ = 0;
  // Every cell ever created, leaf or not: key → is_leaf.
  absl::flat_hash_map<uint64_t, bool> cells_;
  // Leaves indexed by key, for LeafContaining.
  absl::flat_hash_map<uint64_t, OctreeCell> leaves_;
};

VertexKey PackVertex(uint32_t x, uint32_t y, uint32_t z);
std::array<uint32_t, 3> UnpackVertex(VertexKey key);

// A tetrahedron by its vertex keys, positively oriented (det of the edge vectors from the first
// vertex > 0).
using TetKeys = std::array<VertexKey, 4>;

// Appends the J1a tetrahedra of `leaf` (which must be a leaf of a balanced tree) to `out`.
void AppendJ1aTetrahedra(const AdaptiveOctree& tree, const OctreeCell& leaf, std::vector<TetKeys>& out);

}  // namespace lsqsurf::extract
