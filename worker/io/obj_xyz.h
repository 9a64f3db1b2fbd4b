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
#include "worker/io/text_scan.h"

namespace lsqsurf::io {

absl::StatusOr<core::TriangleMesh> ParseObj(std::string_view text, std::string_view name);
std::string EncodeObj(const core::TriangleMesh& mesh);

absl::StatusOr<core::PointCloud> ParseXyz(std::string_view text, std::string_view name);

// An XYZ list read a chunk at a time (ParseXyz reads it in one).
class XyzReader {
 public:
  XyzReader(std::string_view text, std::string_view name) : lines_(text), name_(name) {}
  // Appends up to `max_points` points to `cloud` (none at the end of the text). Errors: as
  // ParseXyz, a file without points included.
  absl::Status Read(size_t max_points, core::PointCloud& cloud);
  size_t offset() const { return lines_.offset(); }  // Bytes read so far.

 private:
  internal::LineReader lines_;
  std::string name_;
  int columns_ = 0;  // 3 or 6 once a point was read.
};
// Writes "x y z" or, with normals, "x y z nx ny nz" lines.
std::string EncodeXyz(const core::PointCloud& cloud);

}  // namespace lsqsurf::io
