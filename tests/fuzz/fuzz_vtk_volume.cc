// Legacy VTK volume meshes (unstructured grids, structured points) with scalar fields.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/volume_formats.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)lsqsurf::io::ParseLegacyVtk(std::string_view(reinterpret_cast<const char*>(data), size), "fuzz.vtk");
  return 0;
}
