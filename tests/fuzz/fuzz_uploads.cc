// Uploads as the job service checks them before it accepts a job (JobKind::CheckUploads): a
// surface cloud (Draco), a track job's velocity grid (legacy VTK), a volume's vertices (Draco)
// and cell stream. The first byte picks the method; for two uploads, the next four give the
// first one's length.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>

#include "worker/jobs/method_registry.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace jobs = lsqsurf::jobs;
  if (size < 1) return 0;
  static const char* const kMethods[] = {"iamls", "pu", "track", "volume"};
  const std::string method = kMethods[data[0] % 4];
  std::string rest(reinterpret_cast<const char*>(data) + 1, size - 1);
  jobs::JobSpec spec;
  spec.method = method;
  spec.params = *jobs::DefaultParams(method);
  jobs::Uploads uploads;
  if (method == "iamls" || method == "pu") {
    uploads[jobs::kInputUpload] = rest;
  } else {
    uint32_t first = 0;
    if (rest.size() >= 4) std::memcpy(&first, rest.data(), 4);
    rest.erase(0, std::min<size_t>(4, rest.size()));
    first = static_cast<uint32_t>(std::min<size_t>(first, rest.size()));
    const char* second_slot = method == "track" ? jobs::kVelocityUpload : jobs::kCellsUpload;
    uploads[jobs::kInputUpload] = rest.substr(0, first);
    uploads[second_slot] = rest.substr(first);
    if (method == "track") {
      // The cloud and the velocity grid are read only when the spec says they were uploaded.
      (void)spec.params.Parse("interface", "uploaded");
      (void)spec.params.Parse("field", "uploaded");
    }
  }
  const jobs::InputLimits limits{/*max_points=*/1'000'000, /*min_points=*/16, /*max_cells=*/1'000'000};
  (void)jobs::FindMethod(method)->kind->CheckUploads(spec, uploads, limits);
  return 0;
}
