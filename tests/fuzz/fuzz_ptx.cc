// The scanner text exports (PTX and PTS) as the client reads them, whole and a chunk at a time.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/pts_ptx.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  (void)lsqsurf::io::ParsePtx(bytes, "fuzz.ptx");
  (void)lsqsurf::io::ParsePts(bytes, "fuzz.pts");
  if (auto reader = lsqsurf::io::PtxReader::Open(bytes, "fuzz.ptx"); reader.ok()) {
    lsqsurf::core::PointCloud chunk;
    while ((*reader)->Read(7, chunk).ok() && chunk.size() > 0) chunk = {};
  }
  return 0;
}
