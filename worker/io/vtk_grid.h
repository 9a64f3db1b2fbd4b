// worker/io/vtk_grid.h — vector fields on regular grids in the legacy VTK format.
//
// The accepted subset is what ParaView, VTK and pyvista write for an image of vectors:
//
//   # vtk DataFile Version 2.0..5.1
//   <title line>
//   ASCII | BINARY
//   DATASET STRUCTURED_POINTS
//   DIMENSIONS nx ny nz          (ORIGIN, SPACING or ASPECT_RATIO in any order; defaults 0 and 1)
//   POINT_DATA nx·ny·nz
//   VECTORS <name> float|double
//   <nx·ny·nz·3 values, x fastest; big-endian in BINARY files>
//
// Anything else (other datasets, scalars before the vectors, cell data) is refused with
// kInvalidArgument naming the line and what was expected, so a user can fix the export.
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
