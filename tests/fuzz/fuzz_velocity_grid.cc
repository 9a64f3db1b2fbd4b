// The velocity upload of track jobs: a legacy VTK grid of vectors, as the server receives it.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "worker/io/vtk_grid.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)lsqsurf::io::ParseVtkVectorGrid(std::string_view(reinterpret_cast<const char*>(data), size), "velocity");
  return 0;
}
