// worker/extract/isosurface.h — zero-set extraction on a sparse uniform grid of tetrahedra.
//
// The grid is never dense: extraction starts from the cubes that hold input points and follows
// the surface from cube to cube across the faces it crosses, so memory and time scale with the
// surface area, and the result is closed wherever F is defined (no cut at an arbitrary band).
// Each cube is split into the 6 tetrahedra of its Kuhn (Freudenthal) triangulation along the
// main diagonal; every cube uses the same diagonal direction, so neighbouring cubes share their
// face triangulations and marching tetrahedra yields a crack-free, edge-manifold, consistently
// oriented surface with no ambiguous cases. Crossings are keyed by the grid edge, so triangles
// share vertices; their positions are refined on F along the edge (regula falsi).
// Tetrahedra with a corner where F is unknown (NaN) produce nothing, and triangles with a root
// where F is not `defined` are dropped (the ghost-sheet and hole guard), unless they form a
// small patch inside trusted surface (see `MarchingOptions::max_patch_triangles`).
#pragma once

#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/implicit_function.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"

namespace lsqsurf::extract {

// The core vocabulary, used throughout extraction.
using core::Box3;
using core::FieldGradient;
using core::FieldValue;
using core::ImplicitFunction;
using core::JobContext;
using core::Triangle;
using core::TriangleMesh;
using core::Vec3d;
using core::Vec3f;

// How crossings become triangles; shared by every extractor.
struct MarchingOptions {
  int refine_steps = 3;              // Root-refinement steps per crossing edge (0 = linear only), 0..20.
  bool vertex_normals = true;        // Store normalize(∇F) at each output vertex.
  int max_patch_triangles = 64;      // Untrusted clusters up to this size enclosed by trusted surface are kept
                                     // (pinholes), trusted ones cut off by untrusted surface are dropped
                                     // (specks); 0 = neither.
  double crease_angle = 0;           // Degrees, 0..90: an edge whose end normals differ by more is split on the
                                     // crease it crosses (creases.h); 0 = off.
  double snap_share = 0;             // 0..0.45: a grid corner the surface passes within this share of an edge from
                                     // is moved onto the surface before marching (no slivers there); 0 = off.
  int relax_steps = 0;               // 0..10: steps of tangential relaxation on the surface after marching (relax.h).
  int max_hole_edges = 0;            // Holes whose border is a loop of up to this many edges are closed (holes.h;
                                     // not a user parameter); 0 = off. Not with `trace`.
  bool close_pierced_edges = false;  // Count inside the ends of lattice edges that a part thinner than the
                                     // edge passes through (marching_tets.h; not a user parameter).
  bool trace = false;                // Fill IsosurfaceResult::trace (not a user parameter).
};

absl::Status Validate(const MarchingOptions& options);

// The chord error (see EstimateChordError in j1a_isosurface.h) the adaptive extractors accept by
// default, as a share of the bounding-box diagonal (spot 1M: 38 % fewer triangles than the finest
// cells everywhere, Chamfer within 1 %).
inline constexpr double kDefaultChordError = 2e-5;

// The user-facing options (refine_steps, crease_angle, snap_share, relax_steps), for the tables of
// the methods that expose them.
const core::ParamTable<MarchingOptions>& MarchingParamTable();

struct IsosurfaceParams {
  double cell_size = 0.0;          // Cube edge length in model units; must be > 0.
  int64_t max_cells = 60'000'000;  // Visited cubes before failing with kResourceExhausted.
  MarchingOptions marching;
};

absl::Status Validate(const IsosurfaceParams& params);

struct IsosurfaceStats {
  int64_t cells_visited = 0;        // Cubes whose corners were evaluated.
  int64_t surface_cells = 0;        // Cubes the surface passes through.
  int64_t field_evaluations = 0;    // Corner evaluations (refinement not included).
  int64_t tetrahedra = 0;           // Tetrahedra sign-tested (J1a: of every visited leaf; grid: of the surface cubes).
  int64_t crossings = 0;            // Output vertices.
  int64_t rejected_polygons = 0;    // Triangles dropped because a root lay where F is undefined.
  int64_t restored_triangles = 0;   // Untrusted triangles kept as parts of small pinhole patches.
  int64_t filled_holes = 0;         // Holes of a few edges closed across (MarchingOptions::max_hole_edges).
  int64_t crease_vertices = 0;      // Edges split where they cross a crease.
  int64_t crease_corners = 0;       // Triangles split around a corner.
  int64_t crease_snapped = 0;       // Vertices moved onto a crease that passed next to them.
  int64_t snapped_corners = 0;      // Grid corners moved onto the surface.
  int64_t pierced_corners = 0;      // Corners counted inside (MarchingOptions::close_pierced_edges).
  int64_t relaxed_vertices = 0;     // Vertices moved by the relaxation (once per round; two rounds).
  int64_t flipped_edges = 0;        // Edges flipped after it (relax.h).
  int64_t replaced_faces = 0;       // Kept faces a local re-extraction replaced (PatchJoin).
  int64_t seam_edges = 0;           // Kept edges the patch was joined along.
  int64_t corner_specks = 0;        // Closed specks dropped beside acute corners and creases (PU).
  int64_t corners_left_coarse = 0;  // 1 where finer leaves at corners added components or handles: left out (PU).
  int64_t creases_left_coarse = 0;  // The same for finer leaves along acute creases (PU).
  int64_t topology_checks = 0;      // 1 where a surface without finer leaves was extracted to compare (PU).
  int64_t wall_splits = 0;  // Leaves split where the lattice missed a probe's side (J1aIsosurfaceParams::probes).
  // Wall time of the stages, seconds.
  double tree_seconds = 0;      // Building an adaptive tree (J1a extractors).
  double tracking_seconds = 0;  // Following the surface: corner values and sign tests.
  double marching_seconds = 0;  // Crossings, root refinement, triangles, patch clean-up.
  double crease_seconds = 0;
  double relax_seconds = 0;
};

// Where the parts of an extracted mesh came from, so that a later extraction can replace some of
// them and join its own triangles to the rest exactly (see stitch.h).
struct SurfaceTrace {
  // Per vertex: a hash of the lattice edge the vertex was marched on (never 0), or 0 for a
  // vertex added afterwards (a crease or corner point).
  std::vector<uint64_t> vertex_edges;
  // Per face: the cell whose tetrahedron made it (the extractor's cell key).
  std::vector<uint64_t> face_cells;
};

struct IsosurfaceResult {
  TriangleMesh mesh;
  IsosurfaceStats stats;
  SurfaceTrace trace;  // Empty unless MarchingOptions::trace.
};

// Keeps the faces flagged in `keep` and the vertices they use, renumbered in first-use order, with
// their normals and the trace's entries (when there is one). The mesh has no attributes yet.
void KeepFaces(std::span<const char> keep, TriangleMesh& mesh, SurfaceTrace& trace);

// Closes the holes of an extracted surface whose border is a loop of up to `max_edges` edges, as
// MarchingOptions::max_hole_edges does while marching, for a surface marched with a trace (PU's
// kept surfaces, which the local edits join onto, stay as marched): counts them in
// stats.filled_holes and drops the trace, which no longer covers every face. Holes with a border
// vertex where `keep_open` says so stay (a hole an edit cut on purpose).
void CloseSmallHoles(IsosurfaceResult& result, int max_edges, const std::function<bool(const Vec3f&)>& keep_open = {});

// Extracts {F = 0} near `seeds` (normally the input points: extraction starts in their cubes).
// Errors: kInvalidArgument (bad params, no seeds, grid too large for 21-bit coordinates),
// kResourceExhausted (more than `max_cells` cubes), kCancelled.
absl::StatusOr<IsosurfaceResult> ExtractIsosurface(const ImplicitFunction& field, std::span<const Vec3f> seeds,
                                                   const IsosurfaceParams& params, JobContext& ctx);

}  // namespace lsqsurf::extract
