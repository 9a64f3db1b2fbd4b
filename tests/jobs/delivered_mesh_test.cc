// The mesh a client decodes keeps the engine's topology: decoded with Draco and merged by
// position (as STL export and most tools do), it is as closed and manifold as the engine's own
// mesh, and the job's statistics describe it.
#include "tests/jobs/delivered_mesh.h"

#include <gtest/gtest.h>

#include "tests/test_shapes.h"
#include "worker/core/mesh_metrics.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/surface_job.h"

namespace lsqsurf::jobs {
namespace {

TEST(DeliveredMesh, ACadPartFromOneHundredThousandPoints) {
  ExpectDeliveredKeepsTopology("pu", testing::DrilledBlockCloud(100'000), /*genus=*/1);
}

TEST(DeliveredMesh, ExplicitBitsAreKeptAsAsked) {
  core::LocalJobContext ctx;
  auto result = ReconstructSurface("iamls", *DefaultParams("iamls"), testing::SphereCloud(3000), ctx);
  ASSERT_TRUE(result.ok());
  Statistics statistics;
  ASSERT_TRUE(EncodeResultMesh(result->mesh, 12, &statistics).ok());
  EXPECT_EQ(Statistic(statistics, "delivered_position_bits"), 12);
}

}  // namespace
}  // namespace lsqsurf::jobs
