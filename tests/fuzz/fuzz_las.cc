// LAS files as the client reads them, whole and a chunk at a time.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/las.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  (void)lsqsurf::io::ParseLas(bytes, "fuzz.las");
  if (auto reader = lsqsurf::io::LasReader::Open(bytes, "fuzz.las"); reader.ok()) {
    lsqsurf::core::PointCloud chunk;
    while ((*reader)->Read(7, chunk).ok() && chunk.size() > 0) chunk = {};
  }
  return 0;
}
