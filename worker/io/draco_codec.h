// worker/io/draco_codec.h — Draco compression of point clouds and triangle meshes.
//
// The only place in the product that includes Draco. Every float attribute is quantized:
// Draco silently falls back to its much larger sequential coder when one is left raw. Named
// scalar attributes travel as 1-component GENERIC attributes whose metadata entry "name" holds
// the attribute name. Point-cloud coding (kd-tree, speeds 0–9) reorders points and mesh coding
// (Edgebreaker) reorders vertices; attributes stay attached to their points.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

struct DracoOptions {
  int position_bits = 16;   // Quantization of positions over the bounding box (1..30 bits);
                            // 0 = lossless float positions (larger: sequential coding).
  int normal_bits = 12;     // Quantization of normals (octahedral; 1..30 bits).
  int attribute_bits = 14;  // Quantization of scalar attributes over their range (1..30 bits).
  int speed = 5;            // 0 = smallest output, slowest … 10 = fastest, keeps point order.
};

absl::Status Validate(const DracoOptions& options);

// Errors: kInvalidArgument (empty input, bad options, a NaN or infinite coordinate when positions
// are quantized — quantization would silently corrupt it), kInternal (Draco refused to encode).
absl::StatusOr<std::string> EncodeDracoPointCloud(const core::PointCloud& cloud, const DracoOptions& options);
absl::StatusOr<std::string> EncodeDracoMesh(const core::TriangleMesh& mesh, const DracoOptions& options);

// How many of `vertices` stay apart through the quantization round trip at `bits` bits a coordinate,
// simulated in Draco's float arithmetic (what a client decodes).
int64_t DistinctAfterQuantization(const std::vector<core::Vec3f>& vertices, int bits);
// The fewest position bits from 16 to 30 at which quantization keeps `distinct` positions of `mesh`
// apart (30 when none does).
int FewestPositionBits(const core::TriangleMesh& mesh, int64_t distinct);

enum class DracoGeometry { kPointCloud, kTriangleMesh };
// What the data holds, from its header alone (no decoding). Errors: kInvalidArgument for data
// that is empty, not Draco, or of another geometry type.
absl::StatusOr<DracoGeometry> PeekDracoGeometry(std::string_view bytes);

// Bounds on what a stream may claim, checked on its header before Draco decodes it (Draco
// allocates what the header claims before reading the data; see draco_header.h).
struct DracoDecodeLimits {
  int64_t max_points = 2'000'000'000;  // Points (vertices) of one stream.
  // Memory the decoder may need (as estimated from the header), per byte of the stream. Real
  // data stays below it: a 1M-vertex grid mesh at 11 bits comes to ~1800 times, a 1M-point grid
  // cloud at 11 bits ~85 times; only a cloud of one point repeated a million times goes further.
  int64_t max_expansion = 4096;
  int64_t expansion_allowance_bytes = 32 << 20;  // Granted to every stream on top of that.
};

// Decodes a Draco point cloud, or the vertices of a Draco mesh. Errors: kInvalidArgument with
// Draco's reason for truncated or corrupt data, a header that claims more memory than
// `max_expansion` allows, or a position attribute that is not 3-D; kResourceExhausted for more
// than `max_points` points.
absl::StatusOr<core::PointCloud> DecodeDracoPointCloud(std::string_view bytes, const DracoDecodeLimits& limits = {});
// Decodes a Draco mesh. Errors as above, plus kInvalidArgument when the data is a point cloud.
absl::StatusOr<core::TriangleMesh> DecodeDracoMesh(std::string_view bytes, const DracoDecodeLimits& limits = {});

}  // namespace lsqsurf::io
