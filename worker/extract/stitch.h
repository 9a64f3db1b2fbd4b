// worker/extract/stitch.h — replacing part of an extracted mesh by a newly marched patch.
//
// A local change of F (an edit of a PU function) changes the zero set only in the cells near it.
// Those cells are marched again (the patch) and the kept mesh loses the faces it made there (its
// trace names each face's cell). Both sides of the seam are faces of unchanged cells, so the
// patch's border vertices lie on the same lattice edges as the kept mesh's hole border: they are
// matched by the trace's edge names and become the kept vertices, at their kept (relaxed)
// positions. A kept crease vertex on a seam edge is inserted into the patch face along that edge.
// Every hole edge must be matched, and every patch border edge with both ends on the seam: the
// join is then as closed as the kept mesh was. Anything else is refused (kFailedPrecondition), and
// the caller extracts the whole surface instead.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "absl/container/flat_hash_set.h"
#include "absl/status/statusor.h"
#include "worker/extract/isosurface.h"

namespace lsqsurf::extract {

class PatchJoin {
 public:
  // `kept` and `kept_trace` are the mesh to change and its trace; `cells` the cells marched again;
  // `patch` their raw marching (traced, before creases and relaxation), whose border vertices on
  // the seam are given the kept positions and normals here, and which gains the kept crease
  // vertices on seam edges. Errors: kFailedPrecondition (the two sides do not meet exactly).
  static absl::StatusOr<PatchJoin> Prepare(const TriangleMesh& kept, const SurfaceTrace& kept_trace,
                                           const absl::flat_hash_set<uint64_t>& cells, IsosurfaceResult& patch);

  // One flag per patch vertex (as Prepare left the patch): set on the seam, which must not move.
  std::span<const char> fixed() const { return fixed_; }
  int64_t removed_faces() const { return removed_faces_; }
  int64_t seam_edges() const { return seam_edges_; }

  // The kept mesh without the replaced faces, joined to the finished `patch` (creases and
  // relaxation may have added vertices after the seam's; the vertex attributes are joined by name,
  // a kept one the patch lacks reads 0 there). Fills `trace` for the result. Works in place on
  // `kept`, the mesh Prepare saw (move it in; the remaining kept vertices keep their order).
  TriangleMesh Merge(TriangleMesh kept, SurfaceTrace kept_trace, const IsosurfaceResult& patch,
                     SurfaceTrace& trace) const;

 private:
  std::vector<char> removed_;          // Per kept face.
  std::vector<char> fixed_;            // Per patch vertex.
  std::vector<uint32_t> kept_vertex_;  // Per patch vertex: the kept vertex it is, or UINT32_MAX.
  int64_t removed_faces_ = 0;
  int64_t seam_edges_ = 0;
};

}  // namespace lsqsurf::extract
