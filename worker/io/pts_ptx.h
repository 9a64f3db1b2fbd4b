// worker/io/pts_ptx.h — the text formats terrestrial laser scanners export (Leica's PTS and PTX,
// written by Cyclone, CloudCompare, FARO Scene and most scanner software).
//
// PTS: lines of "x y z", "x y z intensity", "x y z r g b" or "x y z intensity r g b" (the same
// on every line); a line holding one whole number starts a block of that many points (the file's
// count, or each scan's when scans were concatenated), and is otherwise not needed. Colour is
// 0..255; intensity is kept as the file gives it (Leica writes -2048..2047).
//
// PTX: one or more scans, each a header of ten lines — columns, rows, the scanner's position,
// its three axes, and a 4×4 matrix whose last row is the translation (a point p in the scanner's
// frame is at [p 1]·M in the registered one) — and then columns × rows lines of "x y z
// intensity" or "x y z intensity r g b" in the scanner's frame, column by column. A point at
// 0 0 0 is a pixel the scanner got no return for: it is skipped and counted. Points come out in
// the registered frame. Each scan's position is kept (PtxInfo::stations); with more than one
// scan every point carries the attribute "scan", the index of the scan it came from.
//
// Errors are kInvalidArgument naming the file and line. A PTX file's scan headers are all read
// when it is opened (its line counts checked against the file) before a point is handed out.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

// A PTS file a chunk at a time.
class PtsReader {
 public:
  PtsReader(std::string_view text, std::string_view name);
  ~PtsReader();
  PtsReader(const PtsReader&) = delete;
  PtsReader& operator=(const PtsReader&) = delete;
  // Appends up to `max_points` points to `cloud` (none at the end). Errors: a malformed line,
  // a file without points.
  absl::Status Read(size_t max_points, core::PointCloud& cloud);
  size_t offset() const;  // Bytes read so far.

 private:
  struct State;
  std::unique_ptr<State> state_;
};

absl::StatusOr<core::PointCloud> ParsePts(std::string_view text, std::string_view name);

// What a PTX file's scan headers say, and what reading left out.
struct PtxInfo {
  std::vector<core::Vec3d> stations;  // Each scan's scanner position, registered frame.
  uint64_t points = 0;                // Columns × rows over the scans, missing pixels included.
  uint64_t skipped_points = 0;        // Missing pixels (0 0 0) left out, known once read.
};

// A PTX file a chunk at a time.
class PtxReader {
 public:
  // Reads every scan header. Errors: kInvalidArgument.
  static absl::StatusOr<std::unique_ptr<PtxReader>> Open(std::string_view text, std::string name);
  ~PtxReader();
  PtxReader(const PtxReader&) = delete;
  PtxReader& operator=(const PtxReader&) = delete;
  // Appends up to `max_points` kept points to `cloud` (none at the end).
  absl::Status Read(size_t max_points, core::PointCloud& cloud);
  const PtxInfo& info() const;
  size_t offset() const;  // Bytes read so far.

 private:
  struct State;
  explicit PtxReader(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

absl::StatusOr<core::PointCloud> ParsePtx(std::string_view text, std::string_view name, PtxInfo* info = nullptr);

// One scan to write as PTX: its points in the registered frame with the scanner at `station`
// and its axes the registered ones (the identity matrix but for the translation); `grid`
// columns × rows, zero for one column of all the points.
struct PtxScan {
  core::Vec3d station = core::Vec3d::Zero();
  const core::PointCloud* cloud = nullptr;  // Positions, and intensity / red, green, blue when it has them.
  uint64_t columns = 0, rows = 0;           // 0: one column; else columns × rows == cloud->size().
};
std::string EncodePtx(const std::vector<PtxScan>& scans);

}  // namespace lsqsurf::io
