// worker/io/volume_formats.h — volume data files: legacy VTK, VTK XML unstructured grids, raw
// regular volumes, PLY points with values.
//
// Legacy VTK (`.vtk`, ASCII or BINARY big-endian, file versions 2–5.1): datasets
// UNSTRUCTURED_GRID (tetrahedra, hexahedra, wedges, pyramids, linear or quadratic, in either
// vertex order, as core::RepairVolumeMesh takes them; other cell types are refused by name,
// voxels are reordered into hexahedra), STRUCTURED_GRID, STRUCTURED_POINTS and
// RECTILINEAR_GRID (both become hexahedra); every POINT_DATA array (SCALARS with any number of
// components, VECTORS, NORMALS, FIELD arrays) by name. CELL_DATA and other sections are skipped.
// Parsers are strict: a malformed file yields kInvalidArgument naming the section and what was
// expected; counts are checked against the bytes present before anything is allocated.
#pragma once

#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/volume_mesh.h"

namespace lsqsurf::io {

// `name` appears in error messages only.
absl::StatusOr<core::VolumeMesh> ParseLegacyVtk(std::string_view bytes, std::string_view name);

// An UNSTRUCTURED_GRID file (version 4.2 layout) with every field as POINT_DATA.
std::string EncodeLegacyVtk(const core::VolumeMesh& mesh, bool binary);

// A headerless regular volume, x fastest. `layout`: "NXxNYxNZ:TYPE[:SPACING]", TYPE one of
// uint8, int8, uint16, int16, uint32, int32, float32, float64 (little-endian), SPACING one
// number or "sx,sy,sz" (default 1). The field is named `field_name`.
absl::StatusOr<core::VolumeMesh> ParseRawVolume(std::string_view bytes, std::string_view layout,
                                                std::string_view field_name);

// VTK XML unstructured grids (.vtu, what ParaView and most CFD/FEM codes write): every piece,
// DataArrays in ascii, binary (base64) or appended (raw or base64) form, uncompressed or zlib
// (vtkZLibDataCompressor), UInt32 or UInt64 headers, little-endian; point data by name; the
// same cell types and checks as the legacy reader.
absl::StatusOr<core::VolumeMesh> ParseVtu(std::string_view bytes, std::string_view name);

// A PLY point set whose vertex properties other than x, y, z become fields (faces are ignored).
absl::StatusOr<core::VolumeMesh> ParsePlyVolume(std::string_view bytes, std::string_view name);

// By extension: .vtk, .vtu, .ply; raw volumes need their layout and go through ParseRawVolume.
absl::StatusOr<core::VolumeMesh> ReadVolumeFile(const std::string& path);

}  // namespace lsqsurf::io
