// VTK XML unstructured grids (ascii, binary, appended, zlib-compressed).
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/volume_formats.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)lsqsurf::io::ParseVtu(std::string_view(reinterpret_cast<const char*>(data), size), "fuzz.vtu");
  return 0;
}
