// worker/jobs/store/blob_store.h — where a job's bytes live: its uploads and its artifacts.
//
// Blobs are named per job ("input.drc", "mesh.drc", ...). A write is atomic: readers see the old
// blob or the whole new one. Reads stream in chunks, so a large artifact never has to sit in
// memory whole. LocalDirBlobStore keeps them as files, one folder per job; a shared store
// (object storage) for several servers implements the same interface.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/byte_view.h"

namespace lsqsurf::jobs {

// Reads one blob in chunks.
class BlobReader {
 public:
  virtual ~BlobReader() = default;
  virtual int64_t size() const = 0;
  // Up to `max_bytes` more bytes; empty at the end. Errors: kUnavailable.
  virtual absl::StatusOr<std::string> Next(size_t max_bytes) = 0;
};

// The rest of the reader's blob. Errors: those of Next.
absl::StatusOr<std::string> ReadAll(BlobReader& reader);

// The kNotFound every store gives for a blob it does not hold.
absl::Status NoSuchBlob(const std::string& job_id, std::string_view name);

class BlobStore {
 public:
  virtual ~BlobStore() = default;
  // Stores (or replaces) a blob. Errors: kResourceExhausted (the disk is full; nothing of the
  // blob is left behind), kUnavailable.
  virtual absl::Status Put(const std::string& job_id, std::string_view name, std::string_view bytes) = 0;
  // Stores (or replaces) a blob from the file at `path`, which it may take (a rename) rather than
  // copy: the caller removes `path` afterwards if it is still there. Errors: those of Put,
  // kNotFound (no such file).
  virtual absl::Status PutFile(const std::string& job_id, std::string_view name, const std::string& path);
  // Errors: kNotFound (no such blob), kUnavailable.
  virtual absl::StatusOr<std::unique_ptr<BlobReader>> Open(const std::string& job_id, std::string_view name) const = 0;
  // The whole blob. Errors: those of Open.
  absl::StatusOr<std::string> Read(const std::string& job_id, std::string_view name) const;
  // The whole blob, mapped read-only where the store keeps files (no copy on the heap), else
  // read. Errors: those of Open.
  virtual absl::StatusOr<core::ByteView> Map(const std::string& job_id, std::string_view name) const;
  virtual bool Exists(const std::string& job_id, std::string_view name) const = 0;
  // Removes one blob; removing nothing is not an error. Errors: kUnavailable.
  virtual absl::Status Remove(const std::string& job_id, std::string_view name) = 0;
  // Removes every blob of the job; removing nothing is not an error.
  virtual absl::Status RemoveJob(const std::string& job_id) = 0;
  // Bytes that can still be stored, or -1 when the store cannot tell.
  virtual int64_t AvailableBytes() const { return -1; }
  // Removes the blobs of every job `is_job` does not know and whatever a write cut short left
  // behind; returns how many jobs' blobs went. Only safe while nobody else writes to the store
  // (a server with a job store of its own, at start). Errors: kUnimplemented, kUnavailable.
  virtual absl::StatusOr<int> RemoveOrphans(const std::function<bool(const std::string&)>& is_job) {
    (void)is_job;
    return absl::UnimplementedError("this blob store cannot list its jobs");
  }
};

// Blobs as files: <root>/<job id>/<name>, written to a temporary file and renamed.
class LocalDirBlobStore final : public BlobStore {
 public:
  // Creates `root` if missing. Errors: kUnavailable.
  static absl::StatusOr<std::unique_ptr<LocalDirBlobStore>> Open(std::string root);

  absl::Status Put(const std::string& job_id, std::string_view name, std::string_view bytes) override;
  absl::Status PutFile(const std::string& job_id, std::string_view name, const std::string& path) override;
  absl::StatusOr<core::ByteView> Map(const std::string& job_id, std::string_view name) const override;
  absl::StatusOr<std::unique_ptr<BlobReader>> Open(const std::string& job_id, std::string_view name) const override;
  bool Exists(const std::string& job_id, std::string_view name) const override;
  absl::Status Remove(const std::string& job_id, std::string_view name) override;
  absl::Status RemoveJob(const std::string& id) override;
  int64_t AvailableBytes() const override;
  absl::StatusOr<int> RemoveOrphans(const std::function<bool(const std::string&)>& is_job) override;

 private:
  explicit LocalDirBlobStore(std::string root) : root_(std::move(root)) {}
  std::string PathOf(const std::string& job_id, std::string_view name) const;
  // The job's folder, made if missing. Errors: kUnavailable.
  absl::Status MakeJobFolder(const std::string& job_id) const;
  std::string root_;
};

}  // namespace lsqsurf::jobs
