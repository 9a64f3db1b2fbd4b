// worker/volume/stars.h — what each vertex learns from its neighbourhood (its star): the
// least-squares gradient of every field, the local metric and the share of volume it stands for.
//
// Gradients (seed eqs. 14–15; Mavriplis, AIAA 2003-3986): ∇f_i minimises
// Σ_k ω_ik (∇f_i·d_ik − Δf_ik)² over the star, d_ik = x_k − x_i. The seed's ω = exp(−‖d‖²)
// depends on the data's units; here ω = exp(−‖d‖²/h_i²) with h_i the star's mean edge, or
// ω = 1/‖d‖² (Mavriplis' inverse-distance weights, better on curved stretched meshes). A star
// whose 3×3 system is near singular (all its vertices close to a plane) is widened to the
// vertices two edges away; one that stays singular gets the minimum-norm solution.
//
// Metric: C_i = Σ d dᵀ / |star| and M_i = det(C_i)^{1/3} C_i⁻¹ (unit determinant), so that a
// kernel measured in M_i stretches along the mesh's long cell directions. The ratio of its axes
// is capped at `max_anisotropy` so that a sliver cell cannot make the kernel a needle.
//
// Volume share V_i: the sum over the cells at i of cell volume / cell vertices; for a point set,
// the volume of the ball through the k-th neighbour divided by k + 1.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/job_context.h"
#include "worker/volume/volume_mesh.h"

namespace lsqsurf::volume {

enum class GradientWeights : int { kGaussian = 0, kInverseDistance = 1 };

struct StarParams {
  GradientWeights weights = GradientWeights::kGaussian;
  int neighbors = 16;          // k of the k-nearest-neighbour star of a point set without cells.
  double max_anisotropy = 20;  // Largest ratio of the metric's axis lengths.
};

// Symmetric 3×3 stored as xx, yy, zz, xy, xz, yz.
using Sym3 = std::array<float, 6>;

struct VertexStars {
  std::vector<std::vector<Vec3f>> gradients;  // One per requested field, one vector per vertex.
  std::vector<Sym3> metric;                   // M_i, unit determinant.
  std::vector<float> volume;                  // V_i, model units cubed.
  std::vector<float> mean_edge;               // h_i: mean distance to the star's vertices.
  int64_t widened_stars = 0;                  // Stars widened because the system was near singular.
  int64_t singular_stars = 0;                 // Still singular after widening (minimum-norm gradient).
  double mean_star_size = 0;
};

// `fields`: the scalar arrays (1 component) to differentiate, as pointers into `mesh`.
// Errors: kInvalidArgument (fewer than 5 vertices, all vertices coincident), kCancelled.
absl::StatusOr<VertexStars> AnalyseStars(const VolumeMesh& mesh, std::span<const VertexField* const> fields,
                                         const StarParams& params, core::JobContext& ctx);

// The vertices sharing a cell with each vertex (CSR; the vertex itself excluded); for a mesh
// without cells, its `k` nearest neighbours.
struct Adjacency {
  std::vector<uint64_t> start;
  std::vector<uint32_t> neighbor;
  std::span<const uint32_t> of(size_t i) const { return {neighbor.data() + start[i], neighbor.data() + start[i + 1]}; }
};
Adjacency BuildAdjacency(const VolumeMesh& mesh, int k);

}  // namespace lsqsurf::volume
