#include "worker/core/volume_mesh.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::core {
namespace {

using Tet = std::array<uint32_t, 4>;

// A cell type's reference vertices (VTK's parametric coordinates) and its tetrahedra, each
// ordered to positive volume on the reference cell.
struct CellTemplate {
  std::vector<Vec3f> reference;
  std::vector<Tet> tets;
};

CellTemplate MakeTemplate(std::vector<Vec3f> reference, std::vector<Tet> tets) {
  for (Tet& t : tets) {
    if (TetVolume(reference[t[0]], reference[t[1]], reference[t[2]], reference[t[3]]) < 0) std::swap(t[2], t[3]);
  }
  return {std::move(reference), std::move(tets)};
}

const CellTemplate* TemplateFor(uint8_t vtk_type) {
  static const CellTemplate tetra = MakeTemplate({{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}}, {{0, 1, 2, 3}});
  // The six Kuhn tetrahedra around the diagonal 0–6: the same cut in every cell of a structured
  // block, so the faces of neighbouring cells match.
  static const CellTemplate hexahedron =
      MakeTemplate({{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}},
                   {{0, 1, 2, 6}, {0, 1, 5, 6}, {0, 3, 2, 6}, {0, 3, 7, 6}, {0, 4, 5, 6}, {0, 4, 7, 6}});
  // VTK's wedge: the normal of (0, 1, 2) by the right-hand rule points away from (3, 4, 5).
  static const CellTemplate wedge = MakeTemplate({{0, 0, 0}, {0, 1, 0}, {1, 0, 0}, {0, 0, 1}, {0, 1, 1}, {1, 0, 1}},
                                                 {{0, 1, 2, 3}, {1, 2, 3, 4}, {2, 3, 4, 5}});
  static const CellTemplate pyramid =
      MakeTemplate({{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, {0.5f, 0.5f, 1}}, {{0, 1, 2, 4}, {0, 2, 3, 4}});
  switch (vtk_type) {
    case static_cast<uint8_t>(CellType::kTetrahedron): return &tetra;
    case static_cast<uint8_t>(CellType::kHexahedron): return &hexahedron;
    case static_cast<uint8_t>(CellType::kWedge): return &wedge;
    case static_cast<uint8_t>(CellType::kPyramid): return &pyramid;
    default: return nullptr;
  }
}

absl::Status CheckCellGeometry(const VolumeMesh& mesh, size_t c) {
  const auto [volume, longest] = MeasureCell(mesh, c);
  if (longest == 0) {
    return absl::InvalidArgumentError(
        core::StrCat("cell ", c, " (", CellTypeName(mesh.cell_types[c]), "): all its corners lie at one point"));
  }
  if (volume < -kDegenerateVolume * longest * longest * longest) {
    return absl::InvalidArgumentError(
        core::StrCat("cell ", c, " (", CellTypeName(mesh.cell_types[c]),
                     ") is inverted: its vertices are not in VTK's order (negative volume)"));
  }
  return absl::OkStatus();
}

}  // namespace

int CellVertexCount(uint8_t vtk_type) {
  switch (vtk_type) {
    case 24: return 10;
    case 25: return 20;
    case 26: return 15;
    case 27: return 13;
    default: break;
  }
  const CellTemplate* t = TemplateFor(vtk_type);
  return t == nullptr ? 0 : static_cast<int>(t->reference.size());
}

std::string CellTypeName(uint8_t vtk_type) {
  switch (vtk_type) {
    case 1: return "vertex";
    case 2: return "poly vertex";
    case 3: return "line";
    case 4: return "poly line";
    case 5: return "triangle";
    case 6: return "triangle strip";
    case 7: return "polygon";
    case 8: return "pixel";
    case 9: return "quad";
    case 10: return "tetrahedron";
    case 11: return "voxel";
    case 12: return "hexahedron";
    case 13: return "wedge";
    case 14: return "pyramid";
    case 24: return "quadratic tetrahedron";
    case 25: return "quadratic hexahedron";
    case 26: return "quadratic wedge";
    case 27: return "quadratic pyramid";
    case 42: return "polyhedron";
    default: return core::StrCat("VTK cell type ", static_cast<int>(vtk_type));
  }
}

void VolumeMesh::AddCell(CellType type, std::span<const uint32_t> vertices) {
  if (cell_offsets.empty()) cell_offsets.push_back(0);
  cell_types.push_back(static_cast<uint8_t>(type));
  cell_vertices.insert(cell_vertices.end(), vertices.begin(), vertices.end());
  cell_offsets.push_back(static_cast<uint32_t>(cell_vertices.size()));
}

const VertexField* VolumeMesh::FindField(std::string_view name) const {
  for (const VertexField& f : fields) {
    if (f.name == name) return &f;
  }
  return nullptr;
}

std::string DescribeFields(const VolumeMesh& mesh) {
  if (mesh.fields.empty()) return "none";
  std::string out;
  for (const VertexField& f : mesh.fields) {
    core::StrAppend(&out, out.empty() ? "" : ", ", f.name,
                    f.components == 1   ? " (scalar)"
                    : f.components == 3 ? " (vector)"
                                        : core::StrCat(" (", f.components, " components)"));
  }
  return out;
}

void AddStructuredHexahedra(VolumeMesh& mesh, int nx, int ny, int nz) {
  auto id = [&](int i, int j, int k) { return static_cast<uint32_t>((k * ny + j) * nx + i); };
  for (int k = 0; k + 1 < nz; ++k) {
    for (int j = 0; j + 1 < ny; ++j) {
      for (int i = 0; i + 1 < nx; ++i) {
        const std::array<uint32_t, 8> v = {
            id(i, j, k),     id(i + 1, j, k),     id(i + 1, j + 1, k),     id(i, j + 1, k),
            id(i, j, k + 1), id(i + 1, j, k + 1), id(i + 1, j + 1, k + 1), id(i, j + 1, k + 1)};
        mesh.AddCell(CellType::kHexahedron, v);
      }
    }
  }
}

double TetVolume(const Vec3f& a, const Vec3f& b, const Vec3f& c, const Vec3f& d) {
  const Vec3d ab = (b - a).cast<double>(), ac = (c - a).cast<double>(), ad = (d - a).cast<double>();
  return ab.cross(ac).dot(ad) / 6.0;
}

CellExtent MeasureCell(const VolumeMesh& mesh, size_t cell) {
  const auto v = mesh.cell(cell);
  CellExtent out;
  for (const Tet& t : TemplateFor(mesh.cell_types[cell])->tets) {
    out.volume +=
        TetVolume(mesh.positions[v[t[0]]], mesh.positions[v[t[1]]], mesh.positions[v[t[2]]], mesh.positions[v[t[3]]]);
  }
  for (size_t a = 0; a < v.size(); ++a) {
    for (size_t b = a + 1; b < v.size(); ++b) {
      out.longest = std::max(out.longest, static_cast<double>((mesh.positions[v[a]] - mesh.positions[v[b]]).norm()));
    }
  }
  return out;
}

std::vector<Tet> Tetrahedralize(const VolumeMesh& mesh, size_t cell) {
  std::vector<Tet> out;
  const auto v = mesh.cell(cell);
  for (const Tet& t : TemplateFor(mesh.cell_types[cell])->tets) out.push_back({v[t[0]], v[t[1]], v[t[2]], v[t[3]]});
  return out;
}

std::vector<Tet> Tetrahedralize(const VolumeMesh& mesh) {
  std::vector<Tet> out;
  out.reserve(mesh.cell_count() * 5);
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    const auto v = mesh.cell(c);
    for (const Tet& t : TemplateFor(mesh.cell_types[c])->tets) out.push_back({v[t[0]], v[t[1]], v[t[2]], v[t[3]]});
  }
  return out;
}

absl::Status CheckVolumeStructure(const VolumeMesh& mesh, const VolumeLimits& limits) {
  const size_t n = mesh.vertex_count();
  if (n == 0) return absl::InvalidArgumentError("the volume has no vertices");
  if (static_cast<int64_t>(n) > limits.max_vertices) {
    return absl::ResourceExhaustedError(
        core::StrCat("the volume has ", n, " vertices; this server accepts at most ", limits.max_vertices));
  }
  if (static_cast<int64_t>(mesh.cell_count()) > limits.max_cells) {
    return absl::ResourceExhaustedError(
        core::StrCat("the volume has ", mesh.cell_count(), " cells; this server accepts at most ", limits.max_cells));
  }
  for (size_t i = 0; i < n; ++i) {
    if (!mesh.positions[i].allFinite()) {
      return absl::InvalidArgumentError(core::StrCat("vertex ", i, " has a NaN or infinite coordinate"));
    }
  }
  for (const VertexField& f : mesh.fields) {
    if (f.components < 1 || f.values.size() != n * static_cast<size_t>(f.components)) {
      return absl::InvalidArgumentError(core::StrCat("field '", f.name, "' has ", f.values.size(), " values for ", n,
                                                     " vertices of ", f.components, " components"));
    }
  }
  if (!mesh.has_cells()) return absl::OkStatus();
  if (mesh.cell_offsets.size() != mesh.cell_count() + 1 || mesh.cell_offsets.front() != 0 ||
      mesh.cell_offsets.back() != mesh.cell_vertices.size()) {
    return absl::InvalidArgumentError("the cell offsets do not match the cell list");
  }
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    const int expected = CellVertexCount(mesh.cell_types[c]);
    if (expected == 0) {
      return absl::InvalidArgumentError(
          core::StrCat("cell ", c, " is a ", CellTypeName(mesh.cell_types[c]),
                       "; volume meshes may hold tetrahedra, hexahedra, wedges and pyramids (linear or quadratic) "
                       "only"));
    }
    const auto v = mesh.cell(c);
    if (static_cast<int>(v.size()) != expected) {
      return absl::InvalidArgumentError(core::StrCat("cell ", c, " (", CellTypeName(mesh.cell_types[c]), ") has ",
                                                     v.size(), " vertices, not ", expected));
    }
    for (uint32_t index : v) {
      if (index >= n) {
        return absl::InvalidArgumentError(
            core::StrCat("cell ", c, " refers to vertex ", index, " but the volume has ", n, " vertices"));
      }
    }
  }
  return absl::OkStatus();
}

absl::Status ValidateVolumeMesh(const VolumeMesh& mesh, const VolumeLimits& limits) {
  LSQSURF_RETURN_IF_ERROR(CheckVolumeStructure(mesh, limits));
  for (const VertexField& f : mesh.fields) {
    for (size_t i = 0; i < f.values.size(); ++i) {
      if (!std::isfinite(f.values[i])) {
        return absl::InvalidArgumentError(
            core::StrCat("field '", f.name, "' is NaN or infinite at vertex ", i / static_cast<size_t>(f.components)));
      }
    }
  }
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    if (IsQuadraticCell(mesh.cell_types[c])) {
      return absl::InvalidArgumentError(
          core::StrCat("cell ", c, " is a ", CellTypeName(mesh.cell_types[c]), ", which only RepairVolumeMesh takes"));
    }
    LSQSURF_RETURN_IF_ERROR(CheckCellGeometry(mesh, c));
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::core
