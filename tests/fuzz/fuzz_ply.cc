// PLY files as the client reads them (ascii, binary either endianness; points and meshes).
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/ply.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)lsqsurf::io::ParsePly(std::string_view(reinterpret_cast<const char*>(data), size), "fuzz.ply");
  return 0;
}
