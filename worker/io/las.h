// worker/io/las.h — ASPRS LAS files (versions 1.0 to 1.4), uncompressed, point formats 0 to 10.
//
// Positions are the records' integers times the header's scale plus its offset, computed in
// double. Where the coordinates are so large that float would lose the file's own precision
// (georeferenced scans: a float is 0.25 apart at 4,000,000) and the box lies farther from the
// origin than four times its size, every point is moved by
// LasInfo::shift, the centre of the header's box rounded to whole units, and the cloud is in
// that moved frame. Attributes: red, green, blue (0..255: 16-bit colour as the standard
// stores it is divided by 257; a file that stores 8-bit values in the 16-bit fields, as some
// writers do, is recognised by its sample and kept as it is), intensity, classification, and
// the fields of the extra bytes that an Extra Bytes record (user LASF_Spec, id 4, before the
// points or, in 1.4, after them) describes: each of the ten numeric types is an attribute named
// as the record names it (characters other than letters, digits and '_' become '_'; a repeated
// name is numbered on), its scale and offset applied, at most 64 of them; undocumented bytes and
// the deprecated array types are skipped; no-data values are kept as they are.
// Points flagged withheld and points classified as noise (7 low, 18 high) are left out and
// counted. Every count and offset in the header is checked against the bytes present before
// a point is read; a malformed file gives kInvalidArgument naming the header field. LAZ
// (compressed) data is refused with the conversion to make.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

// What a LAS header says, and what reading left out.
struct LasInfo {
  int version_minor = 2;  // 1.minor.
  int point_format = 0;
  uint32_t record_length = 0;  // Bytes per point, extra bytes included.
  uint64_t points = 0;         // As the header says, left-out points included.
  std::array<double, 3> scale = {0.01, 0.01, 0.01};
  std::array<double, 3> offset = {0, 0, 0};
  std::array<double, 3> min = {0, 0, 0}, max = {0, 0, 0};  // The header's box.
  std::array<double, 3> shift = {0, 0, 0};                 // Subtracted from every position (see above).
  bool has_colour = false;
  bool colour_8bit = false;         // The 16-bit colour fields hold values 0..255.
  std::string generating_software;  // As the header names it.
  uint64_t withheld_points = 0;     // Left out: flagged withheld (known once read).
  uint64_t noise_points = 0;        // Left out: classified 7 or 18 (known once read).
};

// Reads a LAS file a chunk of points at a time from `bytes` (which must outlive it).
class LasReader {
 public:
  // Errors: kInvalidArgument (`name` names the file in messages).
  static absl::StatusOr<std::unique_ptr<LasReader>> Open(std::string_view bytes, std::string name);
  ~LasReader();
  LasReader(const LasReader&) = delete;
  LasReader& operator=(const LasReader&) = delete;

  // Appends the next kept points to `cloud`, at most `max_points`; none once all are read.
  absl::Status Read(size_t max_points, core::PointCloud& cloud);  // Never fails once open.
  const LasInfo& info() const;
  // How far into the bytes reading has come: the bytes before it are not read again.
  size_t offset() const;

 private:
  struct State;
  explicit LasReader(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

// The whole cloud; `info`, when given, receives the header and the counts.
absl::StatusOr<core::PointCloud> ParseLas(std::string_view bytes, std::string_view name, LasInfo* info = nullptr);

// How EncodeLas writes.
struct LasWriteOptions {
  int version_minor = 4;  // 1.2 or 1.4.
  // 0..10; a format with colour (2, 3, 5, 7, 8, 10) writes the cloud's red, green and blue.
  int point_format = 7;
  // Of every axis; 0: the power of ten at or below float's own spacing at the cloud's largest
  // coordinate (coarser where the box would not fit 32-bit integers). The offset is the box's
  // lower corner.
  double scale = 0;
};

// A LAS file of `cloud`: positions, colour ×257 where the format has it, and the attributes
// intensity and classification when the cloud has them.
std::string EncodeLas(const core::PointCloud& cloud, const LasWriteOptions& options = {});

}  // namespace lsqsurf::io
