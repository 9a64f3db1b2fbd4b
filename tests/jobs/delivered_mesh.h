// tests/jobs/delivered_mesh.h — checks that the mesh a client decodes keeps the engine's topology.
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include "worker/core/mesh_metrics.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/surface_job.h"

namespace lsqsurf::jobs {

inline double Statistic(const Statistics& statistics, const std::string& name) {
  for (const auto& [n, v] : statistics) {
    if (n == name) return v;
  }
  ADD_FAILURE() << "no statistic " << name;
  return NAN;
}

// `params`: the method's defaults when null. The engine's statistics go to `engine_statistics`.
inline void ExpectDeliveredKeepsTopology(const std::string& method, const core::PointCloud& cloud, int genus,
                                         const core::ParamSet* params = nullptr,
                                         Statistics* engine_statistics = nullptr) {
  core::LocalJobContext ctx;
  auto result = ReconstructSurface(method, params ? *params : *DefaultParams(method), cloud, ctx);
  ASSERT_TRUE(result.ok()) << result.status();
  if (engine_statistics != nullptr) *engine_statistics = result->statistics;
  const core::MeshTopology engine = core::AnalyzeTopology(result->mesh);
  ASSERT_TRUE(engine.watertight()) << "the engine's own mesh is open: nothing to keep";
  EXPECT_EQ(engine.euler_characteristic(), 2 - 2 * genus);

  Statistics statistics;
  auto bytes = EncodeResultMesh(result->mesh, /*position_bits=*/0, &statistics);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  auto decoded = io::DecodeDracoMesh(*bytes);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(core::CountDistinctPositions(decoded->vertices), core::CountDistinctPositions(result->mesh.vertices));
  const core::MeshTopology delivered = core::AnalyzeTopology(core::WeldByPosition(*decoded));
  EXPECT_EQ(delivered.boundary_edges, 0);
  EXPECT_EQ(delivered.non_manifold_edges, 0);
  EXPECT_EQ(delivered.degenerate_faces, engine.degenerate_faces);
  EXPECT_EQ(delivered.components, engine.components);
  EXPECT_EQ(delivered.euler_characteristic(), engine.euler_characteristic());
  EXPECT_EQ(Statistic(statistics, "non_manifold_edges"), delivered.non_manifold_edges);
  EXPECT_EQ(Statistic(statistics, "boundary_edges"), delivered.boundary_edges);
  const double bits = Statistic(statistics, "delivered_position_bits");
  EXPECT_GE(bits, 16);
  EXPECT_LE(bits, 30);
  std::printf("%s, %zu points: %lld faces delivered at %g bits\n", method.c_str(), cloud.size(),
              static_cast<long long>(delivered.faces), bits);
}

}  // namespace lsqsurf::jobs
