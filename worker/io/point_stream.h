// worker/io/point_stream.h — the points of a file a chunk at a time, for clouds larger than the
// memory one would spend on them whole.
//
// PLY files whose vertex element comes first, XYZ, PCD, LAS, PTS and PTX files are read from a read-only
// mapping whose pages are dropped once their points are handed out: the reader holds one chunk
// (a compressed PCD, its inflated block). Other files (OBJ, Draco, PLY with the vertices after
// another element) are read whole and handed out in chunks. Every stream gives the points'
// attributes (colour, intensity, any scalar property) with them.
#pragma once

#include <array>
#include <cstddef>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::io {

// A file mapped read-only. Release() gives back the pages before an offset (read again from the
// file if touched later), so that a sequential reader's resident memory stays small.
class MappedFile {
 public:
  // Errors: kNotFound, kPermissionDenied, kInvalidArgument (not a regular file).
  static absl::StatusOr<std::shared_ptr<const MappedFile>> Open(const std::string& path);
  ~MappedFile();
  MappedFile(const MappedFile&) = delete;
  MappedFile& operator=(const MappedFile&) = delete;

  std::string_view bytes() const { return {data_, size_}; }
  const std::string& path() const { return path_; }
  void Release(size_t before) const;

 private:
  MappedFile(std::string path, const char* data, size_t size) : path_(std::move(path)), data_(data), size_(size) {}
  std::string path_;
  const char* data_;
  size_t size_;
};

class PointStream {
 public:
  virtual ~PointStream() = default;
  // The next points, at most `max_points` (at least 1); an empty cloud after the last. Errors:
  // kInvalidArgument naming the file and where it went wrong.
  virtual absl::StatusOr<core::PointCloud> Next(size_t max_points) = 0;
  // Where the sensors that made the points stood, when the file says: a PCD's VIEWPOINT, a PTX
  // file's scanner positions. With more than one, each point's attribute "scan" says whose it is.
  virtual std::vector<core::Vec3d> sensor_positions() const { return {}; }
  // Subtracted from the file's coordinates to keep float's precision (LasInfo::shift).
  virtual std::array<double, 3> coordinate_shift() const { return {0, 0, 0}; }
};

// Errors: those of MappedFile::Open and of the file's header, and an unsupported extension.
absl::StatusOr<std::unique_ptr<PointStream>> OpenPointStream(const std::string& path);

// A PLY file's vertex element a chunk at a time; nullptr (not an error) when the vertex element
// does not come first, so that it cannot be streamed. Errors: a bad header.
absl::StatusOr<std::unique_ptr<PointStream>> StreamPlyVertices(std::shared_ptr<const MappedFile> file);
// A PCD file a chunk at a time (pcd.h's rules).
absl::StatusOr<std::unique_ptr<PointStream>> StreamPcd(std::shared_ptr<const MappedFile> file);
// An XYZ point list a chunk at a time (ParseXyz's rules).
std::unique_ptr<PointStream> StreamXyz(std::shared_ptr<const MappedFile> file);
// LAS, PTS and PTX files a chunk at a time (las.h's and pts_ptx.h's rules).
absl::StatusOr<std::unique_ptr<PointStream>> StreamLas(std::shared_ptr<const MappedFile> file);
std::unique_ptr<PointStream> StreamPts(std::shared_ptr<const MappedFile> file);
absl::StatusOr<std::unique_ptr<PointStream>> StreamPtx(std::shared_ptr<const MappedFile> file);

}  // namespace lsqsurf::io
