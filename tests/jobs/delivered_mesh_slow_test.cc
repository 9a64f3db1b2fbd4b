// The delivered-mesh check on a large closed scan (see delivered_mesh_test.cc).
#include <gtest/gtest.h>

#include "tests/jobs/delivered_mesh.h"
#include "tests/test_shapes.h"

namespace lsqsurf::jobs {
namespace {

// About half a minute in an optimised build: labelled slow (skipped under
// the sanitizers).
TEST(DeliveredMesh, AClosedScanFromOneMillionPoints) {
  ExpectDeliveredKeepsTopology("pu", testing::TorusCloud(1'000'000, 1.0, 0.35), /*genus=*/1);
}

}  // namespace
}  // namespace lsqsurf::jobs
