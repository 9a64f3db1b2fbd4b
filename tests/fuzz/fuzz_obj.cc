// Wavefront OBJ files as the client reads them.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/obj_xyz.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)lsqsurf::io::ParseObj(std::string_view(reinterpret_cast<const char*>(data), size), "fuzz.obj");
  return 0;
}
