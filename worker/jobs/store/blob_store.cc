#include "worker/jobs/store/blob_store.h"

#include <sys/statvfs.h>

#include <filesystem>
#include <fstream>

#include "worker/core/strings.h"
#include "worker/io/files.h"

namespace lsqsurf::jobs {
namespace {

class FileReader final : public BlobReader {
 public:
  FileReader(std::ifstream in, int64_t size) : in_(std::move(in)), size_(size) {}
  int64_t size() const override { return size_; }
  absl::StatusOr<std::string> Next(size_t max_bytes) override {
    std::string out(max_bytes, '\0');
    in_.read(out.data(), static_cast<std::streamsize>(max_bytes));
    if (in_.bad()) return absl::UnavailableError("the stored data cannot be read");
    out.resize(static_cast<size_t>(in_.gcount()));
    return out;
  }

 private:
  std::ifstream in_;
  int64_t size_;
};

// A write's failure as the store reports it: a full disk is the caller's to wait out.
absl::Status StoreFailure(const absl::Status& write, const std::string& job_id, std::string_view name) {
  if (absl::IsResourceExhausted(write)) {
    return absl::ResourceExhaustedError(core::StrCat("the server's disk is full: cannot store ", name, " of job ",
                                                     job_id, "; try again once jobs have been deleted"));
  }
  return absl::UnavailableError(core::StrCat("cannot store ", name, ": ", write.message()));
}

}  // namespace

absl::Status NoSuchBlob(const std::string& job_id, std::string_view name) {
  return absl::NotFoundError(core::StrCat("job ", job_id, " has no stored ", name));
}

absl::StatusOr<std::string> ReadAll(BlobReader& reader) {
  std::string all;
  all.reserve(static_cast<size_t>(reader.size()));
  for (;;) {
    auto chunk = reader.Next(size_t{1} << 22);
    if (!chunk.ok()) return chunk.status();
    if (chunk->empty()) return all;
    all += *chunk;
  }
}

absl::StatusOr<std::string> BlobStore::Read(const std::string& job_id, std::string_view name) const {
  auto reader = Open(job_id, name);
  if (!reader.ok()) return reader.status();
  return ReadAll(**reader);
}

absl::Status BlobStore::PutFile(const std::string& job_id, std::string_view name, const std::string& path) {
  auto bytes = core::ByteView::MapFile(path);
  if (!bytes.ok()) return bytes.status();
  return Put(job_id, name, bytes->view());
}

absl::StatusOr<core::ByteView> BlobStore::Map(const std::string& job_id, std::string_view name) const {
  auto bytes = Read(job_id, name);
  if (!bytes.ok()) return bytes.status();
  return core::ByteView(*std::move(bytes));
}

absl::StatusOr<std::unique_ptr<LocalDirBlobStore>> LocalDirBlobStore::Open(std::string root) {
  std::error_code ec;
  std::filesystem::create_directories(root, ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot create ", root, ": ", ec.message()));
  return std::unique_ptr<LocalDirBlobStore>(new LocalDirBlobStore(std::move(root)));
}

std::string LocalDirBlobStore::PathOf(const std::string& job_id, std::string_view name) const {
  return core::StrCat(root_, "/", job_id, "/", name);
}

absl::Status LocalDirBlobStore::MakeJobFolder(const std::string& job_id) const {
  std::error_code ec;
  std::filesystem::create_directories(core::StrCat(root_, "/", job_id), ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot create the folder of job ", job_id, ": ", ec.message()));
  return absl::OkStatus();
}

absl::Status LocalDirBlobStore::PutFile(const std::string& job_id, std::string_view name, const std::string& path) {
  if (absl::Status s = MakeJobFolder(job_id); !s.ok()) return s;
  absl::Status s = io::MoveFileAtomically(path, PathOf(job_id, name));
  if (s.ok() || absl::IsNotFound(s)) return s;
  return StoreFailure(s, job_id, name);
}

absl::StatusOr<core::ByteView> LocalDirBlobStore::Map(const std::string& job_id, std::string_view name) const {
  auto bytes = core::ByteView::MapFile(PathOf(job_id, name));
  if (absl::IsNotFound(bytes.status())) return NoSuchBlob(job_id, name);
  return bytes;
}

absl::Status LocalDirBlobStore::Put(const std::string& job_id, std::string_view name, std::string_view bytes) {
  if (absl::Status s = MakeJobFolder(job_id); !s.ok()) return s;
  if (absl::Status s = io::WriteFileAtomically(PathOf(job_id, name), bytes); !s.ok()) {
    return StoreFailure(s, job_id, name);
  }
  return absl::OkStatus();
}

absl::StatusOr<int> LocalDirBlobStore::RemoveOrphans(const std::function<bool(const std::string&)>& is_job) {
  namespace fs = std::filesystem;
  std::error_code ec;
  int removed = 0;
  for (fs::directory_iterator it(root_, ec), end; !ec && it != end; it.increment(ec)) {
    if (!it->is_directory()) continue;
    const std::string id = it->path().filename().string();
    if (!is_job(id)) {
      if (absl::Status s = RemoveJob(id); !s.ok()) return s;
      ++removed;
      continue;
    }
    // A write cut short leaves its temporary file (io::WriteFileAtomically) beside the blobs.
    std::error_code inner;
    for (fs::directory_iterator file(it->path(), inner), done; !inner && file != done; file.increment(inner)) {
      if (file->path().filename().string().find(".tmp.") != std::string::npos) fs::remove(file->path(), inner);
    }
  }
  if (ec) return absl::UnavailableError(core::StrCat("cannot list ", root_, ": ", ec.message()));
  return removed;
}

int64_t LocalDirBlobStore::AvailableBytes() const {
  struct statvfs disk {};
  if (::statvfs(root_.c_str(), &disk) != 0) return -1;
  return static_cast<int64_t>(disk.f_bavail) * static_cast<int64_t>(disk.f_frsize);
}

absl::StatusOr<std::unique_ptr<BlobReader>> LocalDirBlobStore::Open(const std::string& job_id,
                                                                    std::string_view name) const {
  const std::string path = PathOf(job_id, name);
  std::error_code ec;
  const auto size = std::filesystem::file_size(path, ec);
  if (ec) return NoSuchBlob(job_id, name);
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::UnavailableError(core::StrCat("the stored ", name, " of job ", job_id, " cannot be read"));
  return std::make_unique<FileReader>(std::move(in), static_cast<int64_t>(size));
}

bool LocalDirBlobStore::Exists(const std::string& job_id, std::string_view name) const {
  std::error_code ec;
  return std::filesystem::is_regular_file(PathOf(job_id, name), ec);
}

absl::Status LocalDirBlobStore::Remove(const std::string& job_id, std::string_view name) {
  std::error_code ec;
  std::filesystem::remove(PathOf(job_id, name), ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot remove ", name, " of job ", job_id, ": ", ec.message()));
  return absl::OkStatus();
}

absl::Status LocalDirBlobStore::RemoveJob(const std::string& job_id) {
  std::error_code ec;
  std::filesystem::remove_all(core::StrCat(root_, "/", job_id), ec);
  if (ec) return absl::UnavailableError(core::StrCat("cannot remove the files of job ", job_id, ": ", ec.message()));
  return absl::OkStatus();
}

}  // namespace lsqsurf::jobs
