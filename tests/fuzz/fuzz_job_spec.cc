// The proto-to-spec conversion and validation of SubmitJob's first message and of Render's view
// options: any bytes that parse as the message must convert or be refused with a status.
#include <cstddef>
#include <cstdint>

#include "lsqsurf/v1/reconstruction.pb.h"
#include "server/convert.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const int length = static_cast<int>(size);
  lsqsurf::v1::JobSpec spec;
  if (spec.ParseFromArray(data, length)) (void)lsqsurf::server::FromProto(spec);
  lsqsurf::v1::RenderOptions view;
  if (view.ParseFromArray(data, length)) (void)lsqsurf::server::FromProto(view);
  return 0;
}
