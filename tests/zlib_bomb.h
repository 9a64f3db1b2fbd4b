// tests/zlib_bomb.h — a volume cell stream that inflates a thousandfold: one tetrahedron, then
// `zeros` zero bytes, compressed at zlib's best (about 1 MB per GiB), its length declared as
// `declared` bytes (0: truly).
#pragma once

#include <zlib.h>

#include <cstdint>
#include <string>

namespace lsqsurf::testing {

inline std::string CellStreamBomb(uint64_t zeros, uint64_t declared_length = 0) {
  const std::string cell = {'\x01', '\x0a', '\x00', '\x02', '\x02', '\x02'};  // Count 1; a tetra 0 1 2 3.
  std::string window(1 << 20, '\0');
  z_stream z{};
  deflateInit(&z, 9);
  std::string packed;
  const auto pump = [&](const std::string& in, int flush) {
    z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(in.data()));
    z.avail_in = static_cast<uInt>(in.size());
    do {
      z.next_out = reinterpret_cast<Bytef*>(window.data());
      z.avail_out = static_cast<uInt>(window.size());
      deflate(&z, flush);
      packed.append(window.data(), window.size() - z.avail_out);
    } while (z.avail_out == 0);
  };
  pump(cell, Z_NO_FLUSH);
  const std::string block(1 << 20, '\0');
  for (uint64_t done = 0; done < zeros; done += block.size()) pump(block, Z_NO_FLUSH);
  pump("", Z_FINISH);
  deflateEnd(&z);
  std::string bomb = "LQC1";
  for (uint64_t declared = declared_length > 0 ? declared_length : cell.size() + zeros;; declared >>= 7) {
    bomb += static_cast<char>(declared < 0x80 ? declared : (declared & 0x7f) | 0x80);
    if (declared < 0x80) break;
  }
  return bomb + packed;
}

}  // namespace lsqsurf::testing
