// worker/io/files.h — reading and writing geometry files by extension, atomically.
//
// Extensions: .ply, .obj, .xyz / .xyzn / .txt (point lists), .drc (Draco); point clouds only:
// .pcd, .las, and the scanner exports .pts and .ptx (read, not written). Readers load the whole file (bounded by
// `max_bytes`) and hand it to the strict parsers. Formats with no reader here (.laz, .e57) are refused with the
// conversion that makes one.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/io/draco_codec.h"
#include "worker/io/las.h"
#include "worker/io/pcd.h"
#include "worker/io/ply.h"

namespace lsqsurf::io {

enum class FileFormat { kPly, kObj, kXyz, kDraco, kPcd, kLas, kPts, kPtx };

// Every extension FormatFromPath knows, space-separated (for messages and help).
std::string KnownExtensions();

// Errors: kInvalidArgument naming the unsupported extension.
absl::StatusOr<FileFormat> FormatFromPath(std::string_view path);

// Errors: kNotFound, kPermissionDenied, kResourceExhausted (file larger than `max_bytes`).
absl::StatusOr<std::string> ReadFileBytes(const std::string& path, uint64_t max_bytes = uint64_t{4} << 30);

// Writes to a temporary file beside `path`, flushes it to disk and renames it over `path`, so
// readers see the old file or the whole new one, never a partial write.
absl::Status WriteFileAtomically(const std::string& path, std::string_view bytes);
// Moves the file at `from` to `to` as WriteFileAtomically writes one: flushed to disk, then
// renamed into place; across file systems copied (through a mapping, not the heap) and removed.
// Errors: those of WriteFileAtomically, kNotFound (no `from`).
absl::Status MoveFileAtomically(const std::string& from, const std::string& to);

struct WriteOptions {
  PlyFormat ply_format = PlyFormat::kBinaryLittleEndian;
  DracoOptions draco;
};

absl::StatusOr<core::PointCloud> ReadPointCloudFile(const std::string& path);
absl::StatusOr<core::TriangleMesh> ReadMeshFile(const std::string& path);
absl::Status WriteMeshFile(const std::string& path, const core::TriangleMesh& mesh, const WriteOptions& options = {});
absl::Status WritePointCloudFile(const std::string& path, const core::PointCloud& cloud,
                                 const WriteOptions& options = {});

// Conversions between a mesh's vertex data and a point cloud (faces are dropped / absent).
core::PointCloud CloudFromMesh(core::TriangleMesh mesh);
core::TriangleMesh MeshFromCloud(core::PointCloud cloud);

}  // namespace lsqsurf::io
