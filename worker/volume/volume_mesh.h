// worker/volume/volume_mesh.h — the volume engine's names for the volume mesh, which lives in
// worker/core (worker/core/volume_mesh.h) so that the codecs and the client use it without the
// engine.
#pragma once

#include "worker/core/volume_mesh.h"

namespace lsqsurf::volume {

using core::Vec3d;
using core::Vec3f;

using core::AddStructuredHexahedra;
using core::CellType;
using core::CellTypeName;
using core::CellVertexCount;
using core::CheckVolumeStructure;
using core::DescribeFields;
using core::FillMissingValues;
using core::kNoVolumeLimits;
using core::RepairVolumeMesh;
using core::Tetrahedralize;
using core::TetVolume;
using core::ValidateVolumeMesh;
using core::VertexField;
using core::VolumeLimits;
using core::VolumeMesh;
using core::VolumeRepairParams;
using core::VolumeRepairs;

}  // namespace lsqsurf::volume
