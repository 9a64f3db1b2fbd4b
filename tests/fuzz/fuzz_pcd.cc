// PCD files (all three encodings) as the client reads them, whole and a chunk at a time.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/pcd.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  (void)lsqsurf::io::ParsePcd(bytes, "fuzz.pcd");
  if (auto reader = lsqsurf::io::PcdReader::Open(bytes, "fuzz.pcd"); reader.ok()) {
    lsqsurf::core::PointCloud chunk;
    while ((*reader)->Read(7, chunk).ok() && chunk.size() > 0) chunk = {};
  }
  return 0;
}
