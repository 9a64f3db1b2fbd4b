// The Draco wrapper: uploads decoded as point clouds and as meshes, as the server decodes them.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/draco_codec.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  (void)lsqsurf::io::DecodeDracoPointCloud(bytes);
  (void)lsqsurf::io::DecodeDracoMesh(bytes);
  return 0;
}
