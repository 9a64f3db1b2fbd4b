// worker/io/volume_cells.h — what the legacy VTK and the VTK XML readers share: turning a VTK
// cell into the volume mesh's cell arrays. Included by worker/io only.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <utility>
#include <vector>

#include "worker/core/volume_mesh.h"

namespace lsqsurf::io {

// A VTK cell type read as a number, within 0..255. NaN passes through a clamp and converting it
// is undefined, so it becomes 0 (VTK's empty cell, refused later like any unknown type).
inline uint8_t CellKind(double value) {
  return static_cast<uint8_t>(std::isnan(value) ? 0.0 : std::clamp(value, 0.0, 255.0));
}

// One cell of any VTK type (checked later by CheckVolumeStructure); a voxel becomes the
// hexahedron it is, with its last two vertex pairs swapped.
inline void AppendCell(uint8_t type, std::vector<uint32_t>& vertices, core::VolumeMesh& mesh) {
  if (type == 11 && vertices.size() == 8) {
    std::swap(vertices[2], vertices[3]);
    std::swap(vertices[6], vertices[7]);
    type = static_cast<uint8_t>(core::CellType::kHexahedron);
  }
  if (mesh.cell_offsets.empty()) mesh.cell_offsets.push_back(0);
  mesh.cell_types.push_back(type);
  mesh.cell_vertices.insert(mesh.cell_vertices.end(), vertices.begin(), vertices.end());
  mesh.cell_offsets.push_back(static_cast<uint32_t>(mesh.cell_vertices.size()));
}

}  // namespace lsqsurf::io
