#include "worker/core/byte_view.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "worker/core/strings.h"

namespace lsqsurf::core {
namespace {

struct StringHolder final : ByteView::Holder {
  explicit StringHolder(std::string held) : bytes(std::move(held)) { view = bytes; }
  std::string bytes;
};

struct MappingHolder final : ByteView::Holder {
  MappingHolder(void* mapped, size_t mapped_length) : address(mapped), length(mapped_length) {
    view = std::string_view(static_cast<const char*>(address), length);
  }
  ~MappingHolder() override { ::munmap(address, length); }
  MappingHolder(const MappingHolder&) = delete;
  MappingHolder& operator=(const MappingHolder&) = delete;
  void* address;
  size_t length;
};

}  // namespace

ByteView::ByteView(std::string bytes) {
  if (!bytes.empty()) holder_ = std::make_shared<StringHolder>(std::move(bytes));
}

absl::StatusOr<ByteView> ByteView::MapFile(const std::string& path, bool movable) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    const int error = errno;
    if (error == ENOENT) return absl::NotFoundError(StrCat("no file ", path));
    return absl::UnavailableError(StrCat("cannot open ", path, ": ", std::strerror(error)));
  }
  struct stat info {};
  if (::fstat(fd, &info) != 0) {
    const int error = errno;
    ::close(fd);
    return absl::UnavailableError(StrCat("cannot read the size of ", path, ": ", std::strerror(error)));
  }
  ByteView bytes;
  if (movable) bytes.movable_path_ = path;
  if (info.st_size > 0) {
    const auto length = static_cast<size_t>(info.st_size);
    void* address = ::mmap(nullptr, length, PROT_READ, MAP_PRIVATE, fd, 0);
    const int error = errno;
    if (address == MAP_FAILED) {
      ::close(fd);
      return absl::UnavailableError(StrCat("cannot map ", path, ": ", std::strerror(error)));
    }
    // Decoders read it front to back.
    ::madvise(address, length, MADV_SEQUENTIAL);
    bytes.holder_ = std::make_shared<MappingHolder>(address, length);
  }
  ::close(fd);  // The mapping holds the file.
  return bytes;
}

}  // namespace lsqsurf::core
