// worker/io/vtk_grid.h — vector fields on regular grids in the legacy VTK format.
//
// Read by the same legacy VTK reader as volume files (legacy_vtk.cc), so the same files pass:
// ASCII or big-endian BINARY, versions 2 to 5.1, DATASET STRUCTURED_POINTS with DIMENSIONS,
// ORIGIN and SPACING (or ASPECT_RATIO) in any order, and the point data's first VECTORS array
// (float or double, x fastest) as the field; other arrays, cell data and metadata are skipped.
// Anything else (another dataset, no VECTORS, a count that does not match the grid) is refused
// with kInvalidArgument saying what was expected, so a user can fix the export.
#pragma once

#include <array>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

struct VectorGrid {
  std::array<int, 3> dims{};  // Nodes along x, y, z.
  core::Vec3d origin = core::Vec3d::Zero();
  core::Vec3d spacing = core::Vec3d::Ones();
  std::vector<core::Vec3d> values;  // dims[0]·dims[1]·dims[2] vectors, x fastest.
};

inline constexpr int64_t kMaxVectorGridNodes = int64_t{256} * 256 * 256;

// `name` is used in error messages only. Errors: kInvalidArgument (malformed, truncated,
// unsupported, non-finite values, more than kMaxVectorGridNodes nodes, spacing ≤ 0).
absl::StatusOr<VectorGrid> ParseVtkVectorGrid(std::string_view bytes, std::string_view name);

// Writes `grid` as legacy VTK STRUCTURED_POINTS with float vectors (ASCII or BINARY).
std::string EncodeVtkVectorGrid(const VectorGrid& grid, bool binary);

}  // namespace lsqsurf::io
