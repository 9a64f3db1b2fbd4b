// worker/core/volume_mesh.h — scalar and vector data on the vertices of an arbitrary volume
// mesh (or of a bare point set), as every volume input format reads into.
//
// Cells follow VTK's numbering and vertex order (tetrahedron 10, hexahedron 12, wedge 13,
// pyramid 14). Structured inputs become hexahedra, so that everything downstream sees one kind
// of mesh. A mesh without cells is a scattered point set.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::core {

enum class CellType : uint8_t { kTetrahedron = 10, kHexahedron = 12, kWedge = 13, kPyramid = 14 };

// Vertices of a cell type as files and uploads carry it: the linear types (4, 8, 6, 5) and the
// quadratic ones that RepairVolumeMesh linearises (24 tetrahedron 10, 25 hexahedron 20, 26 wedge
// 15, 27 pyramid 13); 0 for any other code.
int CellVertexCount(uint8_t vtk_type);
// VTK 24-27: cells that exist only until RepairVolumeMesh.
bool IsQuadraticCell(uint8_t vtk_type);
// "tetrahedron", ... or VTK's name for an unsupported code ("triangle", "quadratic tetra", ...).
std::string CellTypeName(uint8_t vtk_type);

// A named point-data array: `components` values per vertex (1 = scalar, 3 = vector).
struct VertexField {
  std::string name;
  int components = 1;
  std::vector<float> values;  // vertices × components, vertex-major.
};

struct VolumeMesh {
  std::vector<Vec3f> positions;
  std::vector<uint8_t> cell_types;     // One VTK code per cell.
  std::vector<uint32_t> cell_offsets;  // cells + 1 entries (empty when there are no cells).
  std::vector<uint32_t> cell_vertices;
  std::vector<VertexField> fields;

  size_t vertex_count() const { return positions.size(); }
  size_t cell_count() const { return cell_types.size(); }
  bool has_cells() const { return !cell_types.empty(); }
  std::span<const uint32_t> cell(size_t c) const {
    return {cell_vertices.data() + cell_offsets[c], cell_offsets[c + 1] - cell_offsets[c]};
  }
  void AddCell(CellType type, std::span<const uint32_t> vertices);
  const VertexField* FindField(std::string_view name) const;
};

// The names of the fields, "a (scalar), b (vector)", for error messages.
std::string DescribeFields(const VolumeMesh& mesh);

// Hexahedra of an nx × ny × nz vertex block in x-fastest order (VTK's structured order).
void AddStructuredHexahedra(VolumeMesh& mesh, int nx, int ny, int nz);

// Every cell cut into tetrahedra (hexahedron 6, wedge 3, pyramid 2) with VTK's orientation kept:
// a well-formed cell gives tetrahedra of positive volume. Faces that are not planar are split
// along one diagonal, so neighbouring cells may disagree by a sliver there. Linear cells only.
std::vector<std::array<uint32_t, 4>> Tetrahedralize(const VolumeMesh& mesh);
// The tetrahedra of one linear cell.
std::vector<std::array<uint32_t, 4>> Tetrahedralize(const VolumeMesh& mesh, size_t cell);

// Below a millionth of its longest corner distance cubed a cell has no usable volume (float
// positions carry about 7 digits): a sliver, or a cell collapsed onto a face, edge or axis.
inline constexpr double kDegenerateVolume = 1e-6;

// A linear cell's signed volume (the sum of its tetrahedra's) and the longest distance between
// two of its corners.
struct CellExtent {
  double volume = 0, longest = 0;
  bool degenerate() const { return std::abs(volume) <= kDegenerateVolume * longest * longest * longest; }
};
CellExtent MeasureCell(const VolumeMesh& mesh, size_t cell);

// Signed volume of a tetrahedron (positive when d lies on the side a, b, c turn counter-clockwise to).
double TetVolume(const Vec3f& a, const Vec3f& b, const Vec3f& c, const Vec3f& d);

struct VolumeLimits {
  int64_t max_vertices = 20'000'000;
  int64_t max_cells = 100'000'000;
};
// For data already accepted (a stored upload) and local files: only the checks of content.
inline constexpr VolumeLimits kNoVolumeLimits{INT64_MAX, INT64_MAX};

// What a file or upload must satisfy to be read at all: counts within `limits`
// (kResourceExhausted), finite positions, known cell types (linear or quadratic) with their
// vertex counts, indices within range, fields of the right length (kInvalidArgument naming the
// cell, vertex or field). Values may be NaN (missing) and cells in either order.
absl::Status CheckVolumeStructure(const VolumeMesh& mesh, const VolumeLimits& limits);

struct VolumeRepairParams {
  // The largest share of a field's vertices that may lack a value (NaN or infinite) and still be
  // filled in from their neighbours; beyond it the mesh is refused.
  double max_missing_share = 0.5;
};

// What RepairVolumeMesh changed, for the job's statistics.
struct VolumeRepairs {
  int64_t linearised_cells = 0;  // Quadratic cells: a tetrahedron becomes 8 over its edge nodes,
                                 // the other types their corners' linear cell.
  int64_t reoriented_cells = 0;  // Cells given in the mirrored vertex order (negative volume).
  int64_t degenerate_cells = 0;  // Slivers and collapsed cells (kDegenerateVolume): kept, they
                                 // carry no volume and no point falls inside them.
  int64_t merged_vertices = 0;   // Vertices at the position of another, merged into it (the
                                 // mean of their values).
  int64_t unused_vertices = 0;   // Vertices in no cell, left out.
  int64_t missing_vertices = 0;  // Vertices with a NaN or infinite value, filled in.
};

// The job statistics that count the repairs (the server's statistics, the CLI's summary), in the
// order of RepairCounts.
inline constexpr std::array<std::string_view, 6> kVolumeRepairStatistics{"linearised_cells", "reoriented_cells",
                                                                         "degenerate_cells", "merged_vertices",
                                                                         "unused_vertices",  "missing_vertices"};
inline std::array<int64_t, 6> RepairCounts(const VolumeRepairs& r) {
  return {r.linearised_cells, r.reoriented_cells, r.degenerate_cells,
          r.merged_vertices,  r.unused_vertices,  r.missing_vertices};
}

// The vertices lacking a value in some field (NaN or infinite) get one from the vertices that
// share a cell with them, ring by ring inwards (inverse-distance weights); in a point set without
// cells they are left out. Returns how many there were. Errors: kInvalidArgument when a field
// lacks values at more than `max_missing_share` of the vertices (naming the count and the first)
// or in a whole connected part of the mesh.
absl::StatusOr<int64_t> FillMissingValues(VolumeMesh& mesh, const VolumeRepairParams& params = {});

// Turns a volume mesh as exporters write it into one the engines take (CheckVolumeStructure
// first): quadratic cells linearised, unused vertices left out, missing values filled in,
// duplicate vertices merged, cells reoriented to VTK's order. Errors: kInvalidArgument for what
// has no sensible reading (CheckVolumeStructure's, FillMissingValues', a cell whose corners all
// lie at one point), naming the cell as uploaded.
absl::StatusOr<VolumeRepairs> RepairVolumeMesh(VolumeMesh& mesh, const VolumeRepairParams& params = {});

// What the engines rely on (RepairVolumeMesh's output satisfies it): CheckVolumeStructure, linear
// cells only, no missing values, no cell inverted beyond kDegenerateVolume, no cell whose
// corners all coincide (kInvalidArgument naming the cell, vertex or field).
absl::Status ValidateVolumeMesh(const VolumeMesh& mesh, const VolumeLimits& limits);

}  // namespace lsqsurf::core
