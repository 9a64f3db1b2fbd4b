// worker/extract/holes.h — closing the small holes an extraction leaves (internal).
//
// An MLS field is trusted only where enough samples support it, and a surface whose samples thin
// out for a moment (the few samples on the rim of a wall thinner than the kernel) comes back with
// slits there: the field's zero lies just beyond the trusted band, so its triangles are dropped
// and the ones around them do not enclose them either. A hole of a few edges lies below the
// resolution the method has anyway, so it is closed with the triangles of least total area across
// its border, which put no vertex anywhere the border does not already reach.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <vector>

#include "worker/core/geometry.h"

namespace lsqsurf::extract::internal {

// Closes every hole whose border is a loop of at most `max_edges` edges (3..kMaxHoleEdges) by the
// triangles of least total area across the loop, facing as the faces around it. No edge is made
// twice, so the mesh stays edge-manifold. A vertex where two fans of faces meet (two holes touch
// there, or one hole's border touches itself) is passed on the side of the gap each border edge
// faces, so it is manifold once its holes are closed. Left open: loops through a vertex where
// three fans meet or through an edge two faces run the same way, through a border vertex at the
// position of another one (welded, their borders may close each other), or with a vertex where
// `keep_open` says so. Faces are appended; vertices are not touched. Returns the holes closed.
// Where there is no hole: one pass over the faces.
inline constexpr int kMaxHoleEdges = 64;
int64_t FillSmallHoles(core::TriangleMesh& mesh, int max_edges,
                       const std::function<bool(const core::Vec3f&)>& keep_open = {});

// The border loops of a mesh's holes, as FillSmallHoles walks them: each in the order its
// filling runs (a border edge a→b is b→a in the loop), a vertex where two fans of faces meet
// passed on the side of the gap each border edge faces. Loops through the vertices FillSmallHoles
// leaves open are left out and counted. Reads the faces the mesh has when made.
class HoleBorders {
 public:
  explicit HoleBorders(const core::TriangleMesh& mesh);
  ~HoleBorders();
  HoleBorders(const HoleBorders&) = delete;
  HoleBorders& operator=(const HoleBorders&) = delete;

  // Each closed loop of at most `max_edges` edges (0: any), once.
  std::vector<std::vector<uint32_t>> Loops(size_t max_edges);
  // Loops Loops() left out: through a vertex where three fans meet, an edge two faces run the
  // same way, or border vertices at one position. Counted by a call to Loops(0).
  int64_t tangled_loops() const { return tangled_loops_; }
  // Whether a face made it joined a and b (vertices of the mesh then; false for later ones).
  bool IsEdge(uint32_t a, uint32_t b) const;
  // The indices of those faces around v (v a vertex of the mesh then).
  void FacesAround(uint32_t v, std::vector<uint32_t>& out) const;

 private:
  struct State;
  std::unique_ptr<State> state_;
  int64_t tangled_loops_ = 0;
};

// The triangles of least total cost across `loop` (dynamic programming, O(n³)): cost(a, b, c)
// for each triangle, chords for which `is_edge` holds never used, a vertex the loop passes twice
// taking chords at its first pass only. Appends them to `out` in the loop's orientation; false
// where no triangulation avoids the edges.
bool TriangulateLoop(const std::vector<uint32_t>& loop, const std::vector<core::Vec3f>& vertices,
                     const std::function<bool(uint32_t, uint32_t)>& is_edge,
                     const std::function<double(const core::Vec3f&, const core::Vec3f&, const core::Vec3f&)>& cost,
                     std::vector<core::Triangle>& out);

// A triangle's area: FillSmallHoles's cost.
double TriangleArea(const core::Vec3f& a, const core::Vec3f& b, const core::Vec3f& c);

}  // namespace lsqsurf::extract::internal
