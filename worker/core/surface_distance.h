// worker/core/surface_distance.h — exact point-to-mesh distances and mesh-to-mesh comparison.
//
// The measures of the project's benchmarks (see bench/README.md): both surfaces are sampled
// uniformly by area, and each sample's exact distance to the other mesh is found through an
// AABB tree over its triangles. A second Hausdorff distance also takes every vertex of both
// meshes (a polytope's corners, which area samples miss). Distances are reported as fractions of the reference's
// bounding-box diagonal. The CLI's `compare` and the benchmark runner share this code.
#pragma once

#include <cstdint>
#include <memory>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"

namespace lsqsurf::core {

// Closest-point queries on a fixed triangle mesh (which must outlive the tree).
// Thread safety: queries are const and may run concurrently.
class TriangleTree {
 public:
  explicit TriangleTree(const TriangleMesh& mesh);
  ~TriangleTree();
  TriangleTree(const TriangleTree&) = delete;
  TriangleTree& operator=(const TriangleTree&) = delete;

  struct Hit {
    double distance2 = 0;  // Squared distance to the closest point.
    Vec3d point;           // The closest point on the mesh.
    uint32_t face = 0;     // The face it lies on.
  };
  // The mesh must have at least one face.
  Hit Closest(const Vec3d& query) const;

 private:
  struct Node;
  void Build(uint32_t node, uint32_t begin, uint32_t end, int depth);
  const TriangleMesh& mesh_;
  std::vector<Node> nodes_;
  std::vector<uint32_t> order_;  // Face indices, grouped by leaf.
};

struct CompareParams {
  size_t samples = 1'000'000;  // Samples taken on each surface.
  uint64_t seed = 1;           // Sampling seed (results are reproducible).
};

struct CompareResult {
  double chamfer = 0;                  // ½ (mean ref→cand + mean cand→ref) / diagonal.
  double hausdorff = 0;                // max of both one-sided maxima / diagonal.
  double hausdorff_with_vertices = 0;  // The same with every vertex of both meshes as a sample too.
  double mean_ref_to_cand = 0;         // / diagonal.
  double mean_cand_to_ref = 0;         // / diagonal.
  double normal_consistency = 0;       // Mean |cos| between face normals of closest-point pairs.
  double far_fraction = 0;             // Share of reference samples farther than 1e-3 diagonal.
  double diagonal = 0;                 // Reference bounding-box diagonal (model units).
};

// Errors: kInvalidArgument when either mesh has no faces; kCancelled.
absl::StatusOr<CompareResult> CompareMeshes(const TriangleMesh& reference, const TriangleMesh& candidate,
                                            const CompareParams& params, JobContext& ctx);

}  // namespace lsqsurf::core
