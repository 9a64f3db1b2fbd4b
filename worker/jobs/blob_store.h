// worker/jobs/blob_store.h — where a job's bytes live: its uploads and its artifacts.
//
// Blobs are named per job ("input.drc", "mesh.drc", ...). A write is atomic: readers see the old
// blob or the whole new one. Reads stream in chunks, so a large artifact never has to sit in
// memory whole. LocalDirBlobStore keeps them as files, one folder per job; a shared store
// (object storage) for several servers implements the same interface.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

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

class BlobStore {
 public:
  virtual ~BlobStore() = default;
  // Stores (or replaces) a blob. Errors: kUnavailable.
  virtual absl::Status Put(const std::string& job_id, std::string_view name, std::string_view bytes) = 0;
  // Errors: kNotFound (no such blob), kUnavailable.
  virtual absl::StatusOr<std::unique_ptr<BlobReader>> Open(const std::string& job_id, std::string_view name) const = 0;
  // The whole blob. Errors: those of Open.
  absl::StatusOr<std::string> Read(const std::string& job_id, std::string_view name) const;
  virtual bool Exists(const std::string& job_id, std::string_view name) const = 0;
  // Removes every blob of the job; removing nothing is not an error.
  virtual absl::Status RemoveJob(const std::string& job_id) = 0;
};

// Blobs as files: <root>/<job id>/<name>, written to a temporary file and renamed.
class LocalDirBlobStore final : public BlobStore {
 public:
  // Creates `root` if missing. Errors: kUnavailable.
  static absl::StatusOr<std::unique_ptr<LocalDirBlobStore>> Open(std::string root);

  absl::Status Put(const std::string& job_id, std::string_view name, std::string_view bytes) override;
  absl::StatusOr<std::unique_ptr<BlobReader>> Open(const std::string& job_id, std::string_view name) const override;
  bool Exists(const std::string& job_id, std::string_view name) const override;
  absl::Status RemoveJob(const std::string& job_id) override;

 private:
  explicit LocalDirBlobStore(std::string root) : root_(std::move(root)) {}
  std::string PathOf(const std::string& job_id, std::string_view name) const;
  std::string root_;
};

}  // namespace lsqsurf::jobs
