// worker/core/binary.h — the byte layout of kept precomputations (a volume field, a PU
// function): scalars and length-prefixed arrays of trivially copyable values, in the machine's
// byte order. Such blobs are read back by the server that wrote them (or one of the same build
// on the same architecture); every length is checked against what remains, so a truncated or
// corrupted blob fails to read instead of reading past its end.
#pragma once

#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

namespace lsqsurf::core {

// Appends scalars and arrays (each after its element count).
class BinaryWriter {
 public:
  template <class T>
  void Scalar(T value) {
    static_assert(std::is_trivially_copyable_v<T>);
    out_.append(reinterpret_cast<const char*>(&value), sizeof(T));
  }
  // T is copied as bytes: plain values, or structs of them such as Eigen's fixed-size vectors
  // (which declare copy constructors, so the trait cannot be asserted).
  template <class T>
  void Array(std::span<const T> values) {
    Scalar<uint64_t>(values.size());
    if (!values.empty()) out_.append(reinterpret_cast<const char*>(values.data()), values.size_bytes());
  }
  void Text(std::string_view s) { Array<char>(std::span<const char>(s.data(), s.size())); }
  std::string Take() { return std::move(out_); }

 private:
  std::string out_;
};

// Reads what BinaryWriter wrote; every call returns false (and reads nothing) when the rest of
// the input is too short or an array's count differs from `expected`.
class BinaryReader {
 public:
  explicit BinaryReader(std::string_view in) : in_(in) {}
  template <class T>
  bool Scalar(T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    if (in_.size() - pos_ < sizeof(T)) return false;
    std::memcpy(&value, in_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return true;
  }
  template <class T>
  bool Array(std::vector<T>& values, uint64_t expected = UINT64_MAX) {
    uint64_t count = 0;
    const size_t start = pos_;
    if (!Scalar(count) || (expected != UINT64_MAX && count != expected) || count > (in_.size() - pos_) / sizeof(T)) {
      pos_ = start;
      return false;
    }
    values.resize(count);
    if (count > 0) std::memcpy(static_cast<void*>(values.data()), in_.data() + pos_, count * sizeof(T));
    pos_ += count * sizeof(T);
    return true;
  }
  bool Text(std::string& s) {
    std::vector<char> chars;
    if (!Array(chars)) return false;
    s.assign(chars.begin(), chars.end());
    return true;
  }
  bool AtEnd() const { return pos_ == in_.size(); }

 private:
  std::string_view in_;
  size_t pos_ = 0;
};

}  // namespace lsqsurf::core
