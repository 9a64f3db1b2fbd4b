// worker/io/volume_codec.h — the compressed wire form of a volume upload.
//
// Two parts, both documented in proto/lsqsurf/v1/reconstruction.proto:
//  * the vertices and the chosen scalar fields as a Draco point cloud: POSITION plus one
//    1-component GENERIC attribute per field (metadata entry "name"), quantized, coded
//    sequentially so that the vertex order (which the cells refer to) is kept;
//  * the cells as a connectivity stream: "LQC1", a varint of the payload's length, then the
//    payload compressed with zlib: a varint cell count, and per cell its VTK type byte followed
//    by its vertex indices, each as the zigzag varint of its difference to the previous index
//    (neighbouring cells share vertices, so the differences are small).
#pragma once

#include <span>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/volume_mesh.h"

namespace lsqsurf::io {

struct VolumeCodecOptions {
  int position_bits = 20;  // Quantization of positions over the bounding box, 8..30.
  int value_bits = 20;     // Quantization of field values over their range, 8..30.
};

// Only the named scalar fields travel. Errors: kInvalidArgument (no vertices, a name that is not
// a scalar field of the mesh, non-finite data), kInternal (Draco refused).
absl::StatusOr<std::string> EncodeVolumeVertices(const core::VolumeMesh& mesh, std::span<const std::string> fields,
                                                 const VolumeCodecOptions& options);
// Positions and fields into `mesh` (its cells are left alone). Errors: kInvalidArgument.
absl::Status DecodeVolumeVertices(std::string_view bytes, core::VolumeMesh& mesh);

std::string EncodeCellStream(const core::VolumeMesh& mesh);
// Cells into `mesh`, parsed as the payload inflates (64 KiB of it held at a time). Errors:
// kInvalidArgument (corrupt or truncated stream), kResourceExhausted (more than `max_cells`
// cells, or a payload that inflates past `max_inflated_bytes`). Indices are not checked against
// the vertices here (ValidateVolumeMesh does).
absl::Status DecodeCellStream(std::string_view bytes, int64_t max_cells, uint64_t max_inflated_bytes,
                              core::VolumeMesh& mesh);

}  // namespace lsqsurf::io
