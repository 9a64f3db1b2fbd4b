// worker/core/volume_mesh.h — scalar and vector data on the vertices of an arbitrary volume
// mesh (or of a bare point set), as every volume input format reads into.
//
// Cells follow VTK's numbering and vertex order (tetrahedron 10, hexahedron 12, wedge 13,
// pyramid 14). Structured inputs become hexahedra, so that everything downstream sees one kind
// of mesh. A mesh without cells is a scattered point set.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "worker/core/geometry.h"

namespace lsqsurf::core {

enum class CellType : uint8_t { kTetrahedron = 10, kHexahedron = 12, kWedge = 13, kPyramid = 14 };

// Vertices of a cell type (4, 8, 6, 5); 0 for a code that is not a supported type.
int CellVertexCount(uint8_t vtk_type);
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
// along one diagonal, so neighbouring cells may disagree by a sliver there.
std::vector<std::array<uint32_t, 4>> Tetrahedralize(const VolumeMesh& mesh);

// Signed volume of a tetrahedron (positive when d lies on the side a, b, c turn counter-clockwise to).
double TetVolume(const Vec3f& a, const Vec3f& b, const Vec3f& c, const Vec3f& d);

struct VolumeLimits {
  int64_t max_vertices = 20'000'000;
  int64_t max_cells = 100'000'000;
};
// For data already accepted (a stored upload) and local files: only the checks of content.
inline constexpr VolumeLimits kNoVolumeLimits{INT64_MAX, INT64_MAX};

// Checks what an upload must satisfy before any engine sees it: counts within `limits`
// (kResourceExhausted), finite positions and field values, supported cell types, indices within
// range, no repeated vertex within a cell, no inverted or degenerate cell, fields of the right
// length (kInvalidArgument naming the cell, vertex or field).
absl::Status ValidateVolumeMesh(const VolumeMesh& mesh, const VolumeLimits& limits);

}  // namespace lsqsurf::core
