// worker/jobs/volume_job.h — the volume job kind: a volume mesh or point set with scalar fields
// in (uploads "input": a Draco point cloud of the vertices with one GENERIC attribute per field,
// "cells": the connectivity stream of io/volume_codec.h, absent for point sets), the
// reconstructed field's statistics and, for each requested iso-value, the isosurface out
// (mesh.drc, normals from Q_∇f, the colour field as a vertex attribute), and the precomputed
// field kept (field.lqvf) for probe jobs.
#pragma once

#include <memory>
#include <mutex>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "worker/core/job_context.h"
#include "worker/jobs/job_kind.h"
#include "worker/render/render.h"
#include "worker/volume/volume_field.h"
#include "worker/volume/volume_mesh.h"

namespace lsqsurf::jobs {

struct VolumeJobParams {
  std::string field;        // The scalar field to reconstruct; required.
  std::vector<double> iso;  // Iso-values; empty = no isosurface.
  std::string color_by;     // A second scalar field sampled on the isosurface; empty = none.
  double resolution = 0.5;  // Finest extraction cube edge, share of the median vertex spacing.
  volume::VolumeFieldParams fit;
};

const JobKind& VolumeJobKind();

struct VolumeResult {
  core::TriangleMesh mesh;  // Empty when no iso-value was asked for.
  Statistics statistics;
  std::unique_ptr<volume::VolumeField> field;  // Kept by the service for probes and renders.
};

// A volume field sampled for pictures, and the sampled grid's error against the field.
struct SampledVolume {
  render::VolumeGrid grid;
  double rms_error = 0, max_error = 0;  // Field units, at 2,000 random points inside the data.
};
// `resolution` grid points along the longest side of the field's box; NaN outside the data. The
// grid holds kPictureGridBytesPerPoint per point, at most `max_bytes` in all (the sampling adds a
// slab of points, not a grid). Errors: kResourceExhausted (past max_bytes, said before anything
// is allocated), kCancelled.
inline constexpr int64_t kPictureGridBytesPerPoint = sizeof(float) * 4;  // A value and a gradient.
absl::StatusOr<SampledVolume> SampleVolumeForPicture(const volume::VolumeField& field, int resolution,
                                                     int64_t max_bytes, const core::JobContext* ctx = nullptr);

// A picture of a volume job's kept field, and the sampled grid's error against the field.
struct VolumePicture {
  std::string png;
  render::RenderInfo info;
  double grid_rms_error = 0, grid_max_error = 0;
};

// Draws kept volume fields. The sampled grid of the last field drawn is kept, so the frames of a
// turntable share it. Thread-safe.
class VolumePictures {
 public:
  explicit VolumePictures(int64_t max_grid_bytes) : max_grid_bytes_(max_grid_bytes) {}
  // `job_id` names the field (SerializeVolumeField's `bytes`) in the cache. Errors: kInvalidArgument
  // (unreadable field), kResourceExhausted (a grid past max_grid_bytes), kCancelled, the renderer's.
  absl::StatusOr<VolumePicture> Draw(const std::string& job_id, std::string_view bytes,
                                     const render::RenderParams& params, render::SharedRenderer& renderer,
                                     const core::JobContext* ctx);

 private:
  const int64_t max_grid_bytes_;
  std::mutex mutex_;  // Guards the two below.
  std::string key_;
  std::shared_ptr<const SampledVolume> grid_;
};

// The artifact that keeps a volume job's precomputed field (SerializeVolumeField).
inline constexpr char kVolumeFieldArtifact[] = "field.lqvf";

// Reconstructs a validated volume with a `volume` method's parameters: the field, then the
// isosurfaces. The service and the benchmark's direct mode both run this; the extraction stops
// past what `memory_bytes` holds (0: the engine's own bound).
// Errors: kInvalidArgument, kResourceExhausted, kCancelled.
absl::StatusOr<VolumeResult> ReconstructVolume(const core::ParamSet& params, const volume::VolumeMesh& mesh,
                                               core::JobContext& ctx, int64_t memory_bytes = 0);

}  // namespace lsqsurf::jobs
