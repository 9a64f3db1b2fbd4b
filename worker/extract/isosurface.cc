#include "worker/extract/isosurface.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/status.h"
#include "worker/extract/holes.h"
#include "worker/extract/marching_tets.h"

namespace lsqsurf::extract {
namespace {

// Grid coordinates are packed 20 bits per axis (biased), so a vertex key fits in 60 bits and
// an edge key (vertex key × 8 + direction) in 63.
constexpr int kBits = 20;
constexpr int64_t kBias = int64_t{1} << (kBits - 1);
constexpr int64_t kLimit = kBias - 2;

using Key = uint64_t;

Key Pack(int64_t x, int64_t y, int64_t z) {
  return (static_cast<uint64_t>(x + kBias) << (2 * kBits)) | (static_cast<uint64_t>(y + kBias) << kBits) |
         static_cast<uint64_t>(z + kBias);
}

std::array<int64_t, 3> Unpack(Key k) {
  const uint64_t mask = (uint64_t{1} << kBits) - 1;
  return {static_cast<int64_t>((k >> (2 * kBits)) & mask) - kBias, static_cast<int64_t>((k >> kBits) & mask) - kBias,
          static_cast<int64_t>(k & mask) - kBias};
}

// Corner c of a cube has offset (c & 1, c >> 1 & 1, c >> 2 & 1).
Key CornerKey(Key cell, int c) {
  const auto [x, y, z] = Unpack(cell);
  return Pack(x + (c & 1), y + ((c >> 1) & 1), z + ((c >> 2) & 1));
}

// The 6 Kuhn tetrahedra of a cube: chains 0 ⊂ 1<<a ⊂ 1<<a|1<<b ⊂ 7 over the axis orders.
constexpr std::array<std::array<int, 4>, 6> kTets = {
    {{0, 1, 3, 7}, {0, 1, 5, 7}, {0, 2, 3, 7}, {0, 2, 6, 7}, {0, 4, 5, 7}, {0, 4, 6, 7}}};

// The 4 corners of each face, for the six directions −x, +x, −y, +y, −z, +z.
std::array<int, 4> FaceCorners(int face) {
  const int axis = face / 2, bit = 1 << axis, side = face % 2;
  std::array<int, 4> out{};
  int n = 0;
  for (int c = 0; c < 8; ++c) {
    if (((c & bit) != 0) == (side == 1)) out[static_cast<size_t>(n++)] = c;
  }
  return out;
}

}  // namespace

const core::ParamTable<MarchingOptions>& MarchingParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<MarchingOptions>();
    t->Integer<&MarchingOptions::refine_steps>("refine_steps", 0, 20, "steps",
                                               "root-refinement steps per crossing edge")
        .Real<&MarchingOptions::crease_angle>(
            "crease_angle", 0, 90, "degrees",
            "an output edge whose end normals differ by more is split where it crosses a crease or corner of the "
            "surface; 0 = off")
        .Real<&MarchingOptions::snap_share>(
            "snap_share", 0, 0.45, "",
            "mesh enhancement: a J1a corner that the surface passes within this share of an edge from is moved onto "
            "the surface before extraction, so that no slivers form there; 0 = off")
        .Integer<&MarchingOptions::relax_steps>(
            "relax_steps", 0, 10, "steps",
            "mesh enhancement: steps of tangential relaxation on the surface after extraction (vertices on creases "
            "and borders stay), then edge flips of thin triangles across flat edges and half as many steps again; "
            "0 = off");
    return t;
  }();
  return *table;
}

void CloseSmallHoles(IsosurfaceResult& result, int max_edges, const std::function<bool(const Vec3f&)>& keep_open) {
  result.stats.filled_holes += internal::FillSmallHoles(result.mesh, max_edges, keep_open);
  result.trace = {};
}

void KeepFaces(std::span<const char> keep, TriangleMesh& mesh, SurfaceTrace& trace) {
  const bool traced = !trace.face_cells.empty(), normals = !mesh.normals.empty();
  size_t kept_faces = 0;
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    if (!keep[f]) continue;
    if (traced) trace.face_cells[kept_faces] = trace.face_cells[f];
    mesh.faces[kept_faces++] = mesh.faces[f];
  }
  mesh.faces.resize(kept_faces);
  if (traced) trace.face_cells.resize(kept_faces);
  std::vector<uint32_t> remap(mesh.vertices.size(), UINT32_MAX);
  std::vector<Vec3f> kept_vertices, kept_normals;
  std::vector<uint64_t> kept_edges;
  kept_vertices.reserve(mesh.vertices.size());
  for (auto& f : mesh.faces) {
    for (uint32_t& v : f) {
      if (remap[v] == UINT32_MAX) {
        remap[v] = static_cast<uint32_t>(kept_vertices.size());
        kept_vertices.push_back(mesh.vertices[v]);
        if (normals) kept_normals.push_back(mesh.normals[v]);
        if (traced) kept_edges.push_back(trace.vertex_edges[v]);
      }
      v = remap[v];
    }
  }
  mesh.vertices = std::move(kept_vertices);
  mesh.normals = std::move(kept_normals);
  trace.vertex_edges = std::move(kept_edges);
}

absl::Status Validate(const MarchingOptions& options) { return MarchingParamTable().Validate(options); }

absl::Status Validate(const IsosurfaceParams& params) {
  if (!(params.cell_size > 0.0) || !std::isfinite(params.cell_size)) {
    return absl::InvalidArgumentError("cell_size must be a positive number");
  }
  if (params.max_cells <= 0) return absl::InvalidArgumentError("max_cells must be positive");
  return Validate(params.marching);
}

absl::StatusOr<IsosurfaceResult> ExtractIsosurface(const ImplicitFunction& field, std::span<const Vec3f> seeds,
                                                   const IsosurfaceParams& params, JobContext& ctx) {
  if (absl::Status s = Validate(params); !s.ok()) return s;
  if (seeds.empty()) return absl::InvalidArgumentError("isosurface extraction needs seed points");
  const Box3 box = core::BoundingBox(seeds);
  const double h = params.cell_size;
  if ((box.sizes() / h).maxCoeff() > static_cast<double>(kLimit)) {
    return absl::InvalidArgumentError(
        "cell_size is too small for the extent of the data (more than 500,000 cells per axis)");
  }
  // Half a cell of offset keeps samples on regular grids off the grid vertices.
  const Vec3d origin = box.min() - Vec3d::Constant(0.5 * h);
  auto vertex_position = [&](Key k) {
    const auto [x, y, z] = Unpack(k);
    return Vec3d(origin + h * Vec3d(static_cast<double>(x), static_cast<double>(y), static_cast<double>(z)));
  };

  IsosurfaceStats stats;
  core::SubContext track_ctx(ctx, "tracking surface", 0.0, 0.75);

  absl::flat_hash_set<Key> visited;
  std::vector<Key> frontier;
  for (const Vec3f& p : seeds) {
    const Vec3d g = (p.cast<double>() - origin) / h;
    const Key k = Pack(static_cast<int64_t>(std::floor(g.x())), static_cast<int64_t>(std::floor(g.y())),
                       static_cast<int64_t>(std::floor(g.z())));
    if (visited.insert(k).second) frontier.push_back(k);
  }
  const double seed_cells = static_cast<double>(frontier.size());

  internal::CornerValues corner_values;
  std::vector<Key> surface_cells;
  while (!frontier.empty()) {
    stats.cells_visited += static_cast<int64_t>(frontier.size());
    if (stats.cells_visited > params.max_cells) {
      return absl::ResourceExhaustedError("the surface needs more than " + std::to_string(params.max_cells) +
                                          " grid cells; raise cell_size or the cell limit");
    }
    for (Key cell : frontier) {
      for (int c = 0; c < 8; ++c) corner_values.Need(CornerKey(cell, c));
    }
    LSQSURF_RETURN_IF_ERROR(corner_values.Evaluate(field, vertex_position, stats, ctx));
    const auto& values = corner_values.values();

    std::vector<Key> next;
    for (Key cell : frontier) {
      std::array<FieldValue, 8> corner;
      for (int c = 0; c < 8; ++c) corner[static_cast<size_t>(c)] = values.at(CornerKey(cell, c));
      bool crossed = false;
      for (int face = 0; face < 6; ++face) {
        bool neg = false, pos = false;
        for (int c : FaceCorners(face)) {
          const FieldValue& fv = corner[static_cast<size_t>(c)];
          if (std::isnan(fv.value)) continue;
          (fv.value < 0 ? neg : pos) = true;
        }
        if (!(neg && pos)) continue;
        crossed = true;
        auto [x, y, z] = Unpack(cell);
        const int axis = face / 2, step = face % 2 == 1 ? 1 : -1;
        (axis == 0 ? x : axis == 1 ? y : z) += step;
        if (std::abs(x) > kLimit || std::abs(y) > kLimit || std::abs(z) > kLimit) continue;
        const Key neighbor = Pack(x, y, z);
        if (visited.insert(neighbor).second) next.push_back(neighbor);
      }
      if (crossed) surface_cells.push_back(cell);
    }
    frontier = std::move(next);
    track_ctx.Report(1.0 - std::min(1.0, static_cast<double>(frontier.size()) / std::max(1.0, seed_cells)));
  }
  stats.surface_cells = static_cast<int64_t>(surface_cells.size());
  stats.tetrahedra = static_cast<int64_t>(surface_cells.size() * kTets.size());
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());

  core::SubContext emit_ctx(ctx, "extracting triangles", 0.75, 0.9);
  auto marched = internal::MarchTetrahedra(
      field,
      [&](const internal::TetVisitor& visit) {
        for (Key cell : surface_cells) {
          for (const auto& tet : kTets) {
            visit({CornerKey(cell, tet[0]), CornerKey(cell, tet[1]), CornerKey(cell, tet[2]), CornerKey(cell, tet[3])},
                  static_cast<uint64_t>(cell));
          }
        }
      },
      corner_values.values(), vertex_position, params.marching, stats, emit_ctx);
  if (!marched.ok()) return marched;
  corner_values = {};
  surface_cells = {};
  core::SubContext finish_ctx(ctx, "finishing the surface", 0.9, 1.0);
  LSQSURF_RETURN_IF_ERROR(internal::FinishSurface(field, params.marching, *marched, finish_ctx));
  return marched;
}

}  // namespace lsqsurf::extract
