#include "worker/io/files.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <utility>

#include "worker/core/byte_view.h"
#include "worker/core/strings.h"
#include "worker/io/obj_xyz.h"
#include "worker/io/pts_ptx.h"

namespace lsqsurf::io {

namespace {

// Every extension read or written, and its format.
constexpr std::pair<const char*, FileFormat> kExtensions[] = {
    {".ply", FileFormat::kPly}, {".pcd", FileFormat::kPcd},   {".las", FileFormat::kLas}, {".pts", FileFormat::kPts},
    {".ptx", FileFormat::kPtx}, {".obj", FileFormat::kObj},   {".xyz", FileFormat::kXyz}, {".xyzn", FileFormat::kXyz},
    {".txt", FileFormat::kXyz}, {".drc", FileFormat::kDraco},
};

}  // namespace

std::string KnownExtensions() {
  std::string out;
  for (const auto& [ext, format] : kExtensions) core::StrAppend(&out, out.empty() ? "" : " ", ext);
  return out;
}

absl::StatusOr<FileFormat> FormatFromPath(std::string_view path) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  for (const auto& [known, format] : kExtensions) {
    if (ext == known) return format;
  }
  if (ext == ".laz") {
    return absl::InvalidArgumentError(core::StrCat(
        path,
        ": .laz files cannot be read here (no LAZ library in Debian 12); decompress it to .las first, e.g. with "
        "laszip -i in.laz -o out.las, or pdal translate in.laz out.las"));
  }
  if (ext == ".e57") {
    return absl::InvalidArgumentError(
        core::StrCat(path, ": ", ext,
                     " files cannot be read here (no E57 library in Debian 12); convert the file to .ply, .pcd, "
                     ".las or .ptx first, e.g. with PDAL (pdal translate in.e57 out.las) or CloudCompare"));
  }
  return absl::InvalidArgumentError(
      core::StrCat(path, ": unsupported file type '", ext, "' (use one of ", KnownExtensions(), ")"));
}

namespace {

// The point-cloud-only formats, parsed whole.
absl::StatusOr<core::PointCloud> ParseCloudOnly(FileFormat format, std::string_view bytes, const std::string& path) {
  switch (format) {
    case FileFormat::kXyz: return ParseXyz(bytes, path);
    case FileFormat::kPcd: return ParsePcd(bytes, path);
    case FileFormat::kLas: return ParseLas(bytes, path);
    case FileFormat::kPts: return ParsePts(bytes, path);
    case FileFormat::kPtx: return ParsePtx(bytes, path);
    default: return absl::InternalError("not a point-cloud-only format");
  }
}

bool CloudOnly(FileFormat format) {
  return format == FileFormat::kXyz || format == FileFormat::kPcd || format == FileFormat::kLas ||
         format == FileFormat::kPts || format == FileFormat::kPtx;
}

}  // namespace

absl::StatusOr<std::string> ReadFileBytes(const std::string& path, uint64_t max_bytes) {
  std::error_code ec;
  const auto size = std::filesystem::file_size(path, ec);
  if (ec) {
    if (ec == std::errc::no_such_file_or_directory) return absl::NotFoundError(core::StrCat(path, ": no such file"));
    return absl::PermissionDeniedError(core::StrCat(path, ": ", ec.message()));
  }
  if (size > max_bytes) {
    return absl::ResourceExhaustedError(
        core::StrCat(path, ": file is ", size, " bytes, over the limit of ", max_bytes));
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::PermissionDeniedError(core::StrCat(path, ": cannot open: ", std::strerror(errno)));
  std::string bytes(size, '\0');
  in.read(bytes.data(), static_cast<std::streamsize>(size));
  if (static_cast<uint64_t>(in.gcount()) != size) {
    return absl::DataLossError(core::StrCat(path, ": short read"));
  }
  return bytes;
}

absl::Status WriteFileAtomically(const std::string& path, std::string_view bytes) {
  // A full disk (or quota) says kResourceExhausted wherever it shows: at open, write or flush.
  const auto failed = [&](const char* what, int error) {
    const std::string message = core::StrCat(path, ": ", what, ": ", std::strerror(error));
    if (error == ENOSPC || error == EDQUOT) return absl::ResourceExhaustedError(message);
    return absl::PermissionDeniedError(message);
  };
  const std::string tmp = core::StrCat(path, ".tmp.", ::getpid());
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return failed("cannot create", errno);
  size_t written = 0;
  while (written < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + written, bytes.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      const int error = errno;
      ::close(fd);
      ::unlink(tmp.c_str());
      return absl::ResourceExhaustedError(core::StrCat(path, ": write failed: ", std::strerror(error)));
    }
    written += static_cast<size_t>(n);
  }
  if (::fsync(fd) != 0 || ::close(fd) != 0) {
    const int error = errno;
    ::unlink(tmp.c_str());
    if (error == ENOSPC || error == EDQUOT) return failed("cannot flush to disk", error);
    return absl::DataLossError(core::StrCat(path, ": cannot flush to disk"));
  }
  if (::rename(tmp.c_str(), path.c_str()) != 0) {
    const std::string err = std::strerror(errno);
    ::unlink(tmp.c_str());
    return absl::PermissionDeniedError(core::StrCat(path, ": cannot rename into place: ", err));
  }
  return absl::OkStatus();
}

absl::Status MoveFileAtomically(const std::string& from, const std::string& to) {
  const int fd = ::open(from.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    const int error = errno;
    if (error == ENOENT) return absl::NotFoundError(core::StrCat("no file ", from));
    return absl::PermissionDeniedError(core::StrCat(from, ": cannot open: ", std::strerror(error)));
  }
  const bool flushed = ::fsync(fd) == 0;
  const int flush_error = errno;
  ::close(fd);
  if (!flushed) {
    if (flush_error == ENOSPC || flush_error == EDQUOT) {
      return absl::ResourceExhaustedError(core::StrCat(from, ": cannot flush to disk: ", std::strerror(flush_error)));
    }
    return absl::DataLossError(core::StrCat(from, ": cannot flush to disk"));
  }
  if (::rename(from.c_str(), to.c_str()) == 0) return absl::OkStatus();
  if (errno != EXDEV) {
    return absl::PermissionDeniedError(core::StrCat(to, ": cannot rename into place: ", std::strerror(errno)));
  }
  auto mapped = core::ByteView::MapFile(from);
  if (!mapped.ok()) return mapped.status();
  if (absl::Status s = WriteFileAtomically(to, mapped->view()); !s.ok()) return s;
  ::unlink(from.c_str());
  return absl::OkStatus();
}

core::PointCloud CloudFromMesh(core::TriangleMesh mesh) {
  core::PointCloud cloud;
  cloud.positions = std::move(mesh.vertices);
  cloud.normals = std::move(mesh.normals);
  cloud.attributes = std::move(mesh.vertex_attributes);
  return cloud;
}

core::TriangleMesh MeshFromCloud(core::PointCloud cloud) {
  core::TriangleMesh mesh;
  mesh.vertices = std::move(cloud.positions);
  mesh.normals = std::move(cloud.normals);
  mesh.vertex_attributes = std::move(cloud.attributes);
  return mesh;
}

absl::StatusOr<core::TriangleMesh> ReadMeshFile(const std::string& path) {
  auto format = FormatFromPath(path);
  if (!format.ok()) return format.status();
  auto bytes = ReadFileBytes(path);
  if (!bytes.ok()) return bytes.status();
  switch (*format) {
    case FileFormat::kPly: return ParsePly(*bytes, path);
    case FileFormat::kObj: return ParseObj(*bytes, path);
    case FileFormat::kDraco: {
      auto mesh = DecodeDracoMesh(*bytes);
      if (!mesh.ok()) return absl::InvalidArgumentError(core::StrCat(path, ": ", mesh.status().message()));
      return mesh;
    }
    case FileFormat::kXyz:
    case FileFormat::kPcd:
    case FileFormat::kLas:
    case FileFormat::kPts:
    case FileFormat::kPtx: {
      auto cloud = ParseCloudOnly(*format, *bytes, path);
      if (!cloud.ok()) return cloud.status();
      return MeshFromCloud(*std::move(cloud));
    }
  }
  return absl::InternalError("unreachable");
}

absl::StatusOr<core::PointCloud> ReadPointCloudFile(const std::string& path) {
  auto format = FormatFromPath(path);
  if (!format.ok()) return format.status();
  if (CloudOnly(*format) || *format == FileFormat::kDraco) {
    auto bytes = ReadFileBytes(path);
    if (!bytes.ok()) return bytes.status();
    if (CloudOnly(*format)) return ParseCloudOnly(*format, *bytes, path);
    auto cloud = DecodeDracoPointCloud(*bytes);
    if (!cloud.ok()) return absl::InvalidArgumentError(core::StrCat(path, ": ", cloud.status().message()));
    return cloud;
  }
  auto mesh = ReadMeshFile(path);
  if (!mesh.ok()) return mesh.status();
  return CloudFromMesh(*std::move(mesh));
}

absl::Status WriteMeshFile(const std::string& path, const core::TriangleMesh& mesh, const WriteOptions& options) {
  auto format = FormatFromPath(path);
  if (!format.ok()) return format.status();
  if ((*format == FileFormat::kPcd || *format == FileFormat::kLas) && !mesh.faces.empty()) {
    return absl::InvalidArgumentError(core::StrCat(path, ": a ", std::filesystem::path(path).extension().string(),
                                                   " file holds points only; write the mesh as .ply, .obj or .drc"));
  }
  switch (*format) {
    case FileFormat::kPly: return WriteFileAtomically(path, EncodePly(mesh, options.ply_format));
    case FileFormat::kObj: return WriteFileAtomically(path, EncodeObj(mesh));
    case FileFormat::kDraco: {
      auto bytes = mesh.faces.empty() ? EncodeDracoPointCloud(CloudFromMesh(mesh), options.draco)
                                      : EncodeDracoMesh(mesh, options.draco);
      if (!bytes.ok()) return bytes.status();
      return WriteFileAtomically(path, *bytes);
    }
    case FileFormat::kXyz: return WriteFileAtomically(path, EncodeXyz(CloudFromMesh(mesh)));
    case FileFormat::kPcd:
      return WriteFileAtomically(path, EncodePcd(CloudFromMesh(mesh), PcdEncoding::kBinaryCompressed));
    case FileFormat::kLas: return WriteFileAtomically(path, EncodeLas(CloudFromMesh(mesh)));
    case FileFormat::kPts:
    case FileFormat::kPtx:
      return absl::InvalidArgumentError(
          core::StrCat(path, ": .pts and .ptx are read, not written here; write points as .ply, .pcd or .las"));
  }
  return absl::InternalError("unreachable");
}

absl::Status WritePointCloudFile(const std::string& path, const core::PointCloud& cloud, const WriteOptions& options) {
  return WriteMeshFile(path, MeshFromCloud(cloud), options);
}

}  // namespace lsqsurf::io
