// worker/core/byte_view.h — read-only bytes that are either held in memory or a file mapped
// read-only, so that a large upload can be decoded without a copy of it on the heap.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace lsqsurf::core {

class ByteView {
 public:
  ByteView() = default;
  // Bytes held in memory (tests, small uploads, blobs from a store that cannot map).
  ByteView(std::string bytes);  // NOLINT(google-explicit-constructor): a string is bytes.
  ByteView(const char* bytes) : ByteView(std::string(bytes)) {}  // NOLINT(google-explicit-constructor)

  // The file at `path`, mapped read-only; its pages are the kernel's file cache, read as they
  // are touched and dropped under pressure. The mapping stays valid when the file is renamed or
  // removed. `movable`: whoever takes these bytes may move the file (a spool file handed to a
  // store) rather than copy it. Errors: kNotFound, kUnavailable.
  static absl::StatusOr<ByteView> MapFile(const std::string& path, bool movable = false);

  std::string_view view() const { return holder_ == nullptr ? std::string_view() : holder_->view; }
  operator std::string_view() const { return view(); }  // NOLINT(google-explicit-constructor)
  const char* data() const { return view().data(); }
  size_t size() const { return view().size(); }
  bool empty() const { return size() == 0; }
  // The file it maps when that file was mapped as movable (a blob store may take it by rename);
  // empty otherwise.
  const std::string& movable_path() const { return movable_path_; }

  // The holder of the bytes (a string or a mapping); shared, so copies are cheap.
  struct Holder {
    virtual ~Holder() = default;
    std::string_view view;
  };

 private:
  std::shared_ptr<const Holder> holder_;
  std::string movable_path_;
};

}  // namespace lsqsurf::core
