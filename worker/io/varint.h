// worker/io/varint.h — unsigned LEB128 integers, as Draco writes its counts and the cell stream
// (volume_codec) writes its own.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

namespace lsqsurf::io {

inline void PutVarint(std::string& out, uint64_t v) {
  while (v >= 0x80) {
    out += static_cast<char>((v & 0x7f) | 0x80);
    v >>= 7;
  }
  out += static_cast<char>(v);
}

// Reads one integer at `pos` and moves `pos` past it; false when the data ends inside it.
inline bool GetVarint(std::string_view s, size_t& pos, uint64_t& v) {
  v = 0;
  for (int shift = 0; shift < 64 && pos < s.size(); shift += 7) {
    const auto byte = static_cast<uint8_t>(s[pos++]);
    v |= static_cast<uint64_t>(byte & 0x7f) << shift;
    if ((byte & 0x80) == 0) return true;
  }
  return false;
}

}  // namespace lsqsurf::io
