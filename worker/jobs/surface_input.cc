#include "worker/jobs/surface_input.h"

#include <cmath>
#include <optional>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"

namespace lsqsurf::jobs {
namespace {

absl::Status CheckCloud(const core::PointCloud& cloud, const PointParams& points, const InputLimits& limits) {
  if (cloud.empty()) return absl::InvalidArgumentError("the point cloud is empty");
  if (static_cast<int64_t>(cloud.size()) > limits.max_points) {
    return absl::ResourceExhaustedError(
        core::StrCat("the cloud has ", cloud.size(), " points; this server accepts at most ", limits.max_points));
  }
  if (const int64_t bad = core::FindNonFinite(cloud.positions); bad >= 0) {
    return absl::InvalidArgumentError(core::StrCat("point ", bad, " has a NaN or infinite coordinate"));
  }
  if (cloud.has_normals()) {
    for (size_t i = 0; i < cloud.size(); ++i) {
      const float len = cloud.normals[i].norm();
      // Draco's octahedral coding keeps unit normals within about 1e-3.
      if (!std::isfinite(len) || std::abs(len - 1.0f) > 0.01f) {
        return absl::InvalidArgumentError(core::StrCat(
            "normal ", i, " has length ", len, "; normals must be unit vectors (normalize them before upload)"));
      }
    }
  } else if (!points.estimate_normals) {
    return absl::InvalidArgumentError(
        "the cloud has no normals and estimate_normals is false; upload normals or allow estimation");
  }
  if (static_cast<int64_t>(cloud.size()) < limits.min_points) {
    return absl::InvalidArgumentError(
        core::StrCat("the cloud has only ", cloud.size(), " points; at least ", limits.min_points, " are needed"));
  }
  return absl::OkStatus();
}

// Decodes one part of the upload; a Draco mesh is refused rather than read as its vertices.
absl::StatusOr<core::PointCloud> DecodePart(std::string_view bytes, const std::string& name, int64_t max_points) {
  if (auto type = io::PeekDracoGeometry(bytes); type.ok() && *type == io::DracoGeometry::kTriangleMesh) {
    return absl::InvalidArgumentError(core::StrCat(name,
                                                   ": the upload is a Draco triangle mesh; upload a Draco "
                                                   "point cloud"));
  }
  auto cloud = io::DecodeDracoPointCloud(bytes, {.max_points = max_points});
  if (!cloud.ok()) return core::WithContext(name, cloud.status());
  return cloud;
}

}  // namespace

absl::Status DracoPartsSource::ForEachChunk(const std::function<absl::Status(const core::PointCloud&)>& visit) const {
  for (size_t i = 0; i < parts_.size(); ++i) {
    auto cloud = DecodePart(parts_[i], core::StrCat("input part ", i), io::DracoDecodeLimits{}.max_points);
    if (!cloud.ok()) return cloud.status();
    LSQSURF_RETURN_IF_ERROR(visit(*cloud));
  }
  return absl::OkStatus();
}

// Decodes and checks every part; keeps them whole for a streaming method, else concatenates.
absl::StatusOr<SurfaceInput> DecodeSurfaceInput(const Uploads& uploads, const PointParams& points,
                                                const InputLimits& limits,
                                                const std::function<bool(int64_t points)>& streams) {
  const std::vector<std::string_view> parts = InputParts(uploads);
  if (parts.empty() || parts[0].empty()) return absl::InvalidArgumentError("no input data was uploaded");
  SurfaceInput input;
  core::Box3 bounds;
  std::optional<bool> with_normals;
  for (size_t i = 0; i < parts.size(); ++i) {
    const std::string name = parts.size() == 1 ? "input" : core::StrCat("input part ", i);
    auto cloud = DecodePart(parts[i], name, limits.max_points);
    if (!cloud.ok()) return cloud.status();
    if (const int64_t total = input.points + static_cast<int64_t>(cloud->size()); total > limits.max_points) {
      return absl::ResourceExhaustedError(core::StrCat("parts 0 to ", i, " of the cloud hold ", total,
                                                       " points; this server accepts at most ", limits.max_points));
    }
    InputLimits part_limits = limits;
    part_limits.min_points = parts.size() == 1 ? limits.min_points : 1;
    if (absl::Status s = CheckCloud(*cloud, points, part_limits); !s.ok()) return core::WithContext(name, s);
    if (with_normals.value_or(cloud->has_normals()) != cloud->has_normals()) {
      return absl::InvalidArgumentError(core::StrCat(name, " ", cloud->has_normals() ? "has" : "lacks",
                                                     " normals and part 0 does not; give every part the same "
                                                     "attributes"));
    }
    with_normals = cloud->has_normals();
    input.points += static_cast<int64_t>(cloud->size());
    bounds.extend(core::BoundingBox(cloud->positions));
    // Attributes are kept that every part has, in part 0's order; the others need not agree.
    if (i == 0) {
      input.cloud = *std::move(cloud);
    } else {
      core::AppendCloud(input.cloud, *cloud);
    }
  }
  if (input.points < limits.min_points) {
    return absl::InvalidArgumentError(
        core::StrCat("the cloud has only ", input.points, " points; at least ", limits.min_points, " are needed"));
  }
  input.diagonal = core::Diagonal(bounds);
  // A cloud streamed must carry its normals: estimating them needs every point's neighbours.
  if (parts.size() > 1 && *with_normals && streams(input.points)) {
    input.cloud = {};
    // The uploads' own bytes (a mapping), not copies.
    for (size_t i = 0; i < parts.size(); ++i) input.parts.push_back(uploads.at(InputPartSlot(static_cast<int64_t>(i))));
  }
  return input;
}

}  // namespace lsqsurf::jobs
