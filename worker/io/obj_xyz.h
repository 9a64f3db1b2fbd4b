// worker/io/obj_xyz.h — Wavefront OBJ (geometry only) and XYZ / XYZN text point lists.
//
// OBJ: `v` (extra colour values are ignored), `vn`, and `f` in any of the a, a/b, a//c, a/b/c
// forms with positive or negative (relative) indices; polygons are fan-triangulated; other
// statements are ignored. Normals are kept per vertex when the file has as many `vn` as `v`.
// XYZ: one point per line, either "x y z" or "x y z nx ny nz" (the same on every line); `#`
// starts a comment. Errors are kInvalidArgument with the file name and line number.
#pragma once

#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

absl::StatusOr<core::TriangleMesh> ParseObj(std::string_view text, std::string_view name);
std::string EncodeObj(const core::TriangleMesh& mesh);

absl::StatusOr<core::PointCloud> ParseXyz(std::string_view text, std::string_view name);
// Writes "x y z" or, with normals, "x y z nx ny nz" lines.
std::string EncodeXyz(const core::PointCloud& cloud);

}  // namespace lsqsurf::io
