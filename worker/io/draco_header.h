// worker/io/draco_header.h — what a Draco stream claims to hold, read from its first bytes.
//
// Draco's decoder (libdraco 1.5) sizes its buffers from the counts in the stream before it reads
// the data those counts describe: a few hundred corrupt bytes can make it allocate gigabytes, and
// deeply nested metadata recurses without bound. These claims are read here, without Draco, so
// that a stream can be refused before Draco sees it. Bitstream versions 2.2 and later are read
// (what Draco 1.3 and newer write).
#pragma once

#include <cstdint>
#include <string_view>

#include "absl/status/statusor.h"

namespace lsqsurf::io {

struct DracoClaim {
  bool is_mesh = false;
  uint64_t points = 0;  // Points (vertices) the stream says it holds.
  uint64_t faces = 0;   // Triangles; 0 for point clouds.
  // Bytes per point of the attributes the stream declares (point clouds; 0 for meshes, whose
  // attribute descriptors follow entropy-coded connectivity and are not read here).
  uint64_t attribute_bytes_per_point = 0;
  // A point cloud coded with the KD-tree method: it decodes in another order than it was coded
  // in, so anything that refers to points by index (a volume's cells) cannot use it.
  bool reorders_points = false;
};

// Errors: kInvalidArgument (not Draco, truncated header, an unsupported bitstream version or
// method, metadata nested deeper than 32 levels, or a count that cannot fit in the bytes given).
absl::StatusOr<DracoClaim> ReadDracoClaim(std::string_view bytes);

}  // namespace lsqsurf::io
