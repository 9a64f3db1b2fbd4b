// worker/jobs/surface_job.h — the surface job kind: an oriented (or unoriented) point cloud in,
// a watertight-where-the-data-is triangle mesh out (mesh.drc, and preview.png on request).
//
// Methods: iamls, pu, ramls, apss, aamls, imls. Each method's parameters are one struct below with one
// descriptor table (the engine's own table, its extraction hints and the normal estimation);
// every method hands the job layer the same thing: a mesh from its own extractor (pu) or from
// the one shared extractor given the method's hints (the others).
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/extract/isosurface.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/surface_params.h"
#include "worker/jobs/tile_exchange.h"
#include "worker/mls/algebraic_mls.h"
#include "worker/mls/gaussian_mls.h"
#include "worker/mls/iamls.h"
#include "worker/pu/pu.h"
#include "worker/pu/pu_tiles.h"

namespace lsqsurf::jobs {

struct IamlsJobParams {
  mls::IamlsParams fit;
  double cell_size = 1.5;  // Spacing of the extraction vertices in units of h.
  int refine_steps = 3;    // Root-refinement steps per crossing edge.
  // Splits at most of a leaf whose tetrahedra miss a wall or gap thinner than them, 0..3; -1 =
  // chosen: 2 on clouds the noise choice finds clean, 0 on noisy ones (noise as large as the wall
  // makes the lattice miss it everywhere, and the splits cost more than they mend).
  int wall_levels = -1;
  SurfaceExtractor extractor = SurfaceExtractor::kJ1a;
  PointParams points;  // Normals, viewpoint, attributes, outliers.
  // Components whose bounding-box diagonal is below this many kernel widths (h/ε) are removed:
  // the kernel averages over all of such a component, so it cannot have resolved it; on noisy
  // scans they are bubbles of noise. 0 keeps every component; 0..100.
  double min_component = 2.0;
};

// The MLS surfaces on the shared extractor: the engine's parameters (its `fit` member, the variant,
// set by the method), where to extract, and the normals.
template <class FitParams, auto kFit>
struct MlsJobParams {
  MlsJobParams() { fit.fit = kFit; }
  FitParams fit;
  double cell_size = 1.0;  // Spacing of the extraction vertices in units of h.
  int refine_steps = 3;
  int wall_levels = -1;  // As IamlsJobParams::wall_levels; -1 = 2 (no noise estimate here).
  PointParams points;    // Normals, viewpoint, attributes, outliers.
};
template <mls::AlgebraicFit kFit>
using AlgebraicJobParams = MlsJobParams<mls::AlgebraicMlsParams, kFit>;
using RamlsJobParams = AlgebraicJobParams<mls::AlgebraicFit::kRamls>;
using ApssJobParams = AlgebraicJobParams<mls::AlgebraicFit::kApss>;
template <mls::GaussianFit kFit>
using GaussianJobParams = MlsJobParams<mls::GaussianMlsParams, kFit>;
using AamlsJobParams = GaussianJobParams<mls::GaussianFit::kAdamsonAlexa>;
using ImlsJobParams = GaussianJobParams<mls::GaussianFit::kKolluri>;

struct PuJobParams {
  pu::PuParams fit;
  pu::PuExtractParams extract;
  pu::PuTileParams tiles;
  PointParams points;         // Normals, viewpoint, attributes, outliers.
  bool keep_function = true;  // Store the fitted function (kPuFunctionArtifact) and the traced surface
                              // (kPuSurfaceArtifact) for csg and edit jobs.
};

// The artifact that keeps a PU job's fitted function (pu::SerializePu).
inline constexpr char kPuFunctionArtifact[] = "function.lqpu";
// Beside it, the traced surface extracted from it (pu::SerializeSurface), which an edit job
// changes only near the edit (pu::ExtractEdited).
inline constexpr char kPuSurfaceArtifact[] = "surface.lqsf";

// An artifact job `job_id` kept. Errors: kFailedPrecondition (no such job, not succeeded, or no
// such artifact), others of the store.
absl::StatusOr<std::string> ReadKeptArtifact(RunEnvironment& env, const std::string& job_id, std::string_view name);

// The kept function of job `job_id` (csg and edit jobs read their operands through this).
// Errors: kFailedPrecondition (no such job, not succeeded, or nothing kept, with what to do),
// kInvalidArgument (unreadable), kUnavailable.
absl::StatusOr<std::unique_ptr<pu::PuFunction>> ReadKeptPuFunction(RunEnvironment& env, const std::string& job_id);

const JobKind& SurfaceJobKind();

// Writes a job's artifact at once (ArtifactSink::Write).
using ArtifactWriteFn = std::function<absl::Status(const std::string& name, std::string_view bytes)>;

struct SurfaceResult {
  core::TriangleMesh mesh;  // Empty when delivered in parts.
  int64_t mesh_parts = 0;   // Parts written through ReconstructStreamed's `write`.
  Statistics statistics;
  std::vector<std::pair<std::string, std::string>> kept;  // Artifacts beside the mesh: name, bytes.
};

// Reconstructs a cloud with a method's validated parameters (`params` from the method's
// defaults): normals first when the cloud has none, then the method, then topology statistics.
// The service and the benchmark's direct mode both run this; the extraction stops past what
// `memory_bytes` holds (0: the engines' own bounds); a tiled run keeps its point files and
// spreads its tiles as `tiled` says. Errors: kInvalidArgument,
// kResourceExhausted, kFailedPrecondition (no surface found), kCancelled.
absl::StatusOr<SurfaceResult> ReconstructSurface(const std::string& method, const core::ParamSet& params,
                                                 core::PointCloud cloud, core::JobContext& ctx,
                                                 int64_t memory_bytes = 0, const TiledRun& tiled = {});
// The same for a cloud with normals read in chunks from `source` (`points` in all), by a method
// that streams (pu, tiled): the cloud is never whole in memory. With `write`, the mesh is not
// whole either: each tile's part goes out through it as soon as it is made (mesh_parts, and
// the statistics triangles, vertices and mesh_parts). Errors: as above.
absl::StatusOr<SurfaceResult> ReconstructStreamed(const std::string& method, const core::ParamSet& params,
                                                  const pu::PointSource& source, int64_t points, core::JobContext& ctx,
                                                  int64_t memory_bytes = 0, const ArtifactWriteFn& write = nullptr,
                                                  const TiledRun& tiled = {});

// The Draco bytes of a result mesh at `position_bits` (0: the fewest bits, 16 to 30, at which
// Draco's quantization round trip keeps every distinct vertex position apart, so the decoded
// mesh merged by position keeps the engine's topology). Adds delivered_position_bits,
// encode_seconds and the topology of the mesh as a client decodes and merges it
// (boundary_edges, non_manifold_edges, degenerate_faces, components) to `statistics`.
// Errors: those of the encoder; kCancelled once `ctx` (when given) is, asked between the steps,
// each of which takes seconds on a mesh of millions of faces.
absl::StatusOr<std::string> EncodeResultMesh(const core::TriangleMesh& mesh, int position_bits, Statistics* statistics,
                                             const core::JobContext* ctx = nullptr);

// Size, extraction work and triangle quality (smallest-angle 1st percentile and median, aspect
// ratio 99th percentile, and the share of faces per 5° bin of the smallest angle,
// min_angle_share_0_5 … min_angle_share_55_60) of a result mesh, appended to `statistics`.
void AddMeshStatistics(const core::TriangleMesh& mesh, const extract::IsosurfaceStats& extraction,
                       Statistics* statistics);

// Writes a job's result mesh (mesh.drc, EncodeResultMesh at spec.mesh_position_bits, first among
// the results) and the preview the spec asks for; a preview that cannot be drawn is counted in
// `statistics` (preview_failures), not an error. Errors: the encoder's, kUnavailable (storage).
absl::Status DeliverMesh(const core::TriangleMesh& mesh, const JobSpec& spec, RunEnvironment& env,
                         Statistics* statistics);

}  // namespace lsqsurf::jobs
