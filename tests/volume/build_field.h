// The volume tests' way to fit a field: defaults unless given, a test failure (and null) when
// the fit is refused.
#pragma once

#include <gtest/gtest.h>

#include <memory>
#include <string>
#include <vector>

#include "worker/volume/volume_field.h"

namespace lsqsurf::volume {

inline std::unique_ptr<VolumeField> Build(const VolumeMesh& mesh, const std::string& name,
                                          const VolumeFieldParams& params = {}) {
  core::LocalJobContext ctx;
  const std::vector<std::string> names = {name};
  auto field = BuildVolumeField(mesh, names, params, ctx);
  EXPECT_TRUE(field.ok()) << field.status();
  return field.ok() ? std::move(*field) : nullptr;
}

}  // namespace lsqsurf::volume
