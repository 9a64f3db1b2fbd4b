#include "worker/io/point_stream.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <type_traits>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"
#include "worker/io/obj_xyz.h"
#include "worker/io/pts_ptx.h"

namespace lsqsurf::io {
namespace {

absl::Status OpenError(const std::string& path, int error) {
  const std::string why = core::StrCat(path, ": ", std::strerror(error));
  if (error == ENOENT) return absl::NotFoundError(core::StrCat(path, ": no such file"));  // As ReadFileBytes.
  if (error == EACCES || error == EPERM) return absl::PermissionDeniedError(why);
  return absl::InvalidArgumentError(why);
}

// A reader (XyzReader, PcdReader, LasReader, PtsReader, PtxReader) over a file's mapping: each
// chunk read gives back the pages before it.
template <class Reader>
class MappedStream final : public PointStream {
 public:
  MappedStream(std::shared_ptr<const MappedFile> file, std::unique_ptr<Reader> reader,
               std::vector<core::Vec3d> sensors = {})
      : file_(std::move(file)), reader_(std::move(reader)), sensors_(std::move(sensors)) {
    // Readers that looked through the file when they opened (PTX's scan headers, LAS's colour
    // sample) leave pages behind; they are read again from the cache when needed.
    file_->Release(file_->bytes().size());
  }
  absl::StatusOr<core::PointCloud> Next(size_t max_points) override {
    core::PointCloud cloud;
    LSQSURF_RETURN_IF_ERROR(reader_->Read(std::max<size_t>(max_points, 1), cloud));
    file_->Release(reader_->offset());
    return cloud;
  }
  std::vector<core::Vec3d> sensor_positions() const override { return sensors_; }
  std::array<double, 3> coordinate_shift() const override {
    if constexpr (std::is_same_v<Reader, LasReader>) return reader_->info().shift;
    return {0, 0, 0};
  }

 private:
  std::shared_ptr<const MappedFile> file_;
  std::unique_ptr<Reader> reader_;
  std::vector<core::Vec3d> sensors_;
};

// A cloud read whole, handed out in chunks.
class WholeCloudStream final : public PointStream {
 public:
  explicit WholeCloudStream(core::PointCloud cloud) : cloud_(std::move(cloud)) {}
  absl::StatusOr<core::PointCloud> Next(size_t max_points) override {
    const size_t begin = next_, end = std::min(cloud_.size(), begin + std::max<size_t>(max_points, 1));
    next_ = end;
    core::PointCloud chunk;
    chunk.positions.assign(cloud_.positions.begin() + static_cast<ptrdiff_t>(begin),
                           cloud_.positions.begin() + static_cast<ptrdiff_t>(end));
    if (cloud_.has_normals()) {
      chunk.normals.assign(cloud_.normals.begin() + static_cast<ptrdiff_t>(begin),
                           cloud_.normals.begin() + static_cast<ptrdiff_t>(end));
    }
    for (const core::ScalarAttribute& a : cloud_.attributes) {
      if (a.values.size() != cloud_.size()) continue;
      chunk.attributes.push_back({a.name, std::vector<float>(a.values.begin() + static_cast<ptrdiff_t>(begin),
                                                             a.values.begin() + static_cast<ptrdiff_t>(end))});
    }
    return chunk;
  }

 private:
  core::PointCloud cloud_;
  size_t next_ = 0;
};

}  // namespace

absl::StatusOr<std::shared_ptr<const MappedFile>> MappedFile::Open(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return OpenError(path, errno);
  struct stat info {};
  if (::fstat(fd, &info) != 0 || !S_ISREG(info.st_mode)) {
    ::close(fd);
    return absl::InvalidArgumentError(core::StrCat(path, ": not a regular file"));
  }
  const auto size = static_cast<size_t>(info.st_size);
  const char* data = "";
  if (size > 0) {
    void* mapped = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE, fd, 0);
    if (mapped == MAP_FAILED) {
      const int error = errno;
      ::close(fd);
      return OpenError(path, error);
    }
    ::madvise(mapped, size, MADV_SEQUENTIAL);
    data = static_cast<const char*>(mapped);
  }
  ::close(fd);  // The mapping stays valid.
  return std::shared_ptr<const MappedFile>(new MappedFile(path, data, size));
}

MappedFile::~MappedFile() {
  if (size_ > 0) ::munmap(const_cast<char*>(data_), size_);
}

void MappedFile::Release(size_t before) const {
  const auto page = static_cast<size_t>(::sysconf(_SC_PAGESIZE));
  const size_t whole = std::min(before, size_) / page * page;
  // Clean file pages: dropping them only costs a read should they be touched again.
  if (whole > 0) ::madvise(const_cast<char*>(data_), whole, MADV_DONTNEED);
}

absl::StatusOr<std::unique_ptr<PointStream>> OpenPointStream(const std::string& path) {
  auto format = FormatFromPath(path);
  if (!format.ok()) return format.status();
  if (*format != FileFormat::kObj && *format != FileFormat::kDraco) {
    auto file = MappedFile::Open(path);
    if (!file.ok()) return file.status();
    switch (*format) {
      case FileFormat::kXyz: return StreamXyz(*std::move(file));
      case FileFormat::kPcd: return StreamPcd(*std::move(file));
      case FileFormat::kLas: return StreamLas(*std::move(file));
      case FileFormat::kPts: return StreamPts(*std::move(file));
      case FileFormat::kPtx: return StreamPtx(*std::move(file));
      default: break;
    }
    auto stream = StreamPlyVertices(*std::move(file));
    if (!stream.ok() || *stream != nullptr) return stream;
  }
  auto cloud = ReadPointCloudFile(path);
  if (!cloud.ok()) return cloud.status();
  return std::make_unique<WholeCloudStream>(*std::move(cloud));
}

absl::StatusOr<std::unique_ptr<PointStream>> StreamPcd(std::shared_ptr<const MappedFile> file) {
  auto reader = PcdReader::Open(file->bytes(), file->path());
  if (!reader.ok()) return reader.status();
  std::vector<core::Vec3d> sensors;
  if (const PcdInfo& info = (*reader)->info(); info.has_viewpoint) {
    sensors.emplace_back(info.viewpoint[0], info.viewpoint[1], info.viewpoint[2]);
  }
  return std::make_unique<MappedStream<PcdReader>>(std::move(file), *std::move(reader), std::move(sensors));
}

absl::StatusOr<std::unique_ptr<PointStream>> StreamLas(std::shared_ptr<const MappedFile> file) {
  auto reader = LasReader::Open(file->bytes(), file->path());
  if (!reader.ok()) return reader.status();
  return std::make_unique<MappedStream<LasReader>>(std::move(file), *std::move(reader));
}

absl::StatusOr<std::unique_ptr<PointStream>> StreamPtx(std::shared_ptr<const MappedFile> file) {
  auto reader = PtxReader::Open(file->bytes(), file->path());
  if (!reader.ok()) return reader.status();
  std::vector<core::Vec3d> sensors = (*reader)->info().stations;
  return std::make_unique<MappedStream<PtxReader>>(std::move(file), *std::move(reader), std::move(sensors));
}

std::unique_ptr<PointStream> StreamPts(std::shared_ptr<const MappedFile> file) {
  auto reader = std::make_unique<PtsReader>(file->bytes(), file->path());
  return std::make_unique<MappedStream<PtsReader>>(std::move(file), std::move(reader));
}

std::unique_ptr<PointStream> StreamXyz(std::shared_ptr<const MappedFile> file) {
  auto reader = std::make_unique<XyzReader>(file->bytes(), file->path());
  return std::make_unique<MappedStream<XyzReader>>(std::move(file), std::move(reader));
}

}  // namespace lsqsurf::io
