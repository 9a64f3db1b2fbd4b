// worker/io/ply.h — Stanford PLY: ascii, binary little endian and binary big endian.
//
// Reads the `vertex` element (x, y, z required; nx, ny, nz optional; every other scalar
// property becomes a named attribute) and the `face` element (list property `vertex_indices`
// or `vertex_index`; polygons are fan-triangulated). Other elements are skipped. The parser is
// strict: a malformed file yields kInvalidArgument naming the header line, or the element and
// byte offset (binary) or line (ascii) where it went wrong. Counts in the header are checked
// against the bytes present before anything is allocated.
#pragma once

#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

enum class PlyFormat { kAscii, kBinaryLittleEndian, kBinaryBigEndian };

// `name` is used in error messages only (normally the file path).
absl::StatusOr<core::TriangleMesh> ParsePly(std::string_view bytes, std::string_view name);

// Vertices (with normals and attributes when present) and faces; attributes as float, except
// red, green and blue together, which are written as uchar (0..255), as viewers read colour.
std::string EncodePly(const core::TriangleMesh& mesh, PlyFormat format);

}  // namespace lsqsurf::io
