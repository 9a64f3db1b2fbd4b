// worker/io/pcd.h — Point Cloud Data files as the Point Cloud Library writes them (PCD v0.5 to
// v0.7): DATA ascii, binary, and binary_compressed (LZF, each field's values stored together).
//
// Fields: x, y and z are required; normal_x, normal_y and normal_z give normals when all three are
// there and every kept point has a finite one (else they are dropped and estimated later, and
// PcdInfo says so); rgb or rgba (packed 0x(AA)RRGGBB in 4 bytes, F or U as PCL writes them)
// become the attributes red, green and blue (0..255, as a PLY's uchar colour reads); every other
// field of one element becomes a float attribute of its name (intensity, label, curvature, ...).
// Fields of several elements (descriptors) and padding ("_") are skipped. A point whose position
// is not finite (an organized cloud's missing pixel) is skipped and counted. Every count in the
// header is checked against the bytes present, and a compressed block against what LZF can
// inflate, before anything is allocated; a malformed file gives kInvalidArgument naming the
// header line, or the point where it went wrong.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

enum class PcdEncoding { kAscii, kBinary, kBinaryCompressed };

// What a PCD header says, and what reading left out.
struct PcdInfo {
  PcdEncoding encoding = PcdEncoding::kAscii;
  uint64_t width = 0;   // Points a row; the whole count for an unorganized cloud.
  uint64_t height = 1;  // Rows: above 1 for an organized cloud (a depth image's grid).
  uint64_t points = 0;  // As the header says, skipped points included.
  // VIEWPOINT: the sensor's position (tx ty tz) and orientation (qw qx qy qz) in the cloud's
  // frame; PCL writes 0 0 0 1 0 0 0 when it knows no better.
  std::array<double, 7> viewpoint = {0, 0, 0, 1, 0, 0, 0};
  bool has_viewpoint = false;    // The header had a VIEWPOINT line.
  uint64_t skipped_points = 0;   // Points with a non-finite position, left out (known once read).
  bool normals_dropped = false;  // normal_* fields there, but some kept point's were not finite.
};

// Reads a PCD file a chunk of points at a time from `bytes` (which must outlive it): ascii and
// binary straight from the bytes, binary_compressed from the block it inflates once.
class PcdReader {
 public:
  // Errors: kInvalidArgument (`name` names the file in messages).
  static absl::StatusOr<std::unique_ptr<PcdReader>> Open(std::string_view bytes, std::string name);
  ~PcdReader();
  PcdReader(const PcdReader&) = delete;
  PcdReader& operator=(const PcdReader&) = delete;

  // Appends the next kept points to `cloud`, at most `max_points`; none once all are read.
  absl::Status Read(size_t max_points, core::PointCloud& cloud);
  const PcdInfo& info() const;
  // How far into the bytes reading has come: the bytes before it are not read again.
  size_t offset() const;

 private:
  struct State;
  explicit PcdReader(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

// The whole cloud; `info`, when given, receives the header and the counts. Errors: as PcdReader.
absl::StatusOr<core::PointCloud> ParsePcd(std::string_view bytes, std::string_view name, PcdInfo* info = nullptr);

// A PCD v0.7 file of `cloud`: x y z, normal_x normal_y normal_z when it has normals, then each
// attribute as an F4 field, except red, green and blue together, which are written as PCL's
// packed rgb. `viewpoint` goes in the VIEWPOINT line.
std::string EncodePcd(const core::PointCloud& cloud, PcdEncoding encoding,
                      const std::array<double, 7>& viewpoint = {0, 0, 0, 1, 0, 0, 0});

}  // namespace lsqsurf::io
