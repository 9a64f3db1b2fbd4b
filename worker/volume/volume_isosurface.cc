#include "worker/volume/volume_isosurface.h"

#include <algorithm>
#include <cmath>

#include "worker/core/implicit_function.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/j1a_isosurface.h"

namespace lsqsurf::volume {
namespace {

// F = Q_f − iso, defined inside the data's domain.
class LevelFunction final : public core::ImplicitFunction {
 public:
  LevelFunction(const VolumeField& field, int index, double iso) : field_(field), index_(index), iso_(iso) {}
  core::FieldValue Value(const Vec3d& x) const override {
    const VolumeField::Sample s = field_.Evaluate(x, index_);
    return {s.value - iso_, std::isfinite(s.value) && field_.InDomain(x, s.weight)};
  }
  core::FieldGradient ValueAndGradient(const Vec3d& x) const override {
    const VolumeField::Sample s = field_.Evaluate(x, index_);
    return {s.value - iso_, s.gradient, std::isfinite(s.value) && field_.InDomain(x, s.weight)};
  }
  double ValueOnly(const Vec3d& x) const override { return field_.Evaluate(x, index_).value - iso_; }
  absl::Status ValueOnlyBatch(std::span<const Vec3d> xs, std::span<double> out,
                              const core::JobContext* ctx) const override {
    std::vector<VolumeField::Sample> samples(xs.size());
    LSQSURF_RETURN_IF_ERROR(field_.EvaluateBatch(xs, index_, samples, ctx));
    for (size_t k = 0; k < xs.size(); ++k) out[k] = samples[k].value - iso_;
    return absl::OkStatus();
  }

 private:
  const VolumeField& field_;
  int index_;
  double iso_;
};

// Vertices near which the data's linear model puts the level.
std::vector<Vec3f> Seeds(const VolumeField& field, int index, double iso) {
  const auto x = field.positions();
  const auto f = field.data_values(index);
  const auto g = field.data_gradients(index);
  const auto h = field.data_spacing();
  std::vector<Vec3f> seeds;
  for (size_t i = 0; i < x.size(); ++i) {
    if (std::abs(f[i] - iso) <= 1.5 * g[i].norm() * h[i]) seeds.push_back(x[i]);
  }
  return seeds;
}

}  // namespace

absl::StatusOr<core::TriangleMesh> ExtractVolumeIsosurface(const VolumeField& field,
                                                           const VolumeIsosurfaceParams& params,
                                                           core::JobContext& ctx) {
  if (params.iso_values.empty()) return absl::InvalidArgumentError("give at least one iso-value");
  if (!(params.resolution >= 0.05 && params.resolution <= 2)) {
    return absl::InvalidArgumentError(core::StrCat("resolution=", params.resolution, " must be within [0.05, 2]"));
  }
  core::TriangleMesh out;
  core::ScalarAttribute level{"iso", {}};
  for (size_t k = 0; k < params.iso_values.size(); ++k) {
    const double iso = params.iso_values[k];
    const auto levels = static_cast<double>(params.iso_values.size());
    core::SubContext sub(ctx, core::StrCat("isosurface ", iso), static_cast<double>(k) / levels,
                         static_cast<double>(k + 1) / levels);
    const std::vector<Vec3f> seeds = Seeds(field, params.field, iso);
    if (seeds.empty()) {
      const auto f = field.data_values(params.field);
      const auto [lo, hi] = std::minmax_element(f.begin(), f.end());
      return absl::InvalidArgumentError(core::StrCat("iso-value ", iso, " is not reached: field '",
                                                     field.field_names()[params.field], "' spans [", *lo, ", ", *hi,
                                                     "]"));
    }
    const LevelFunction level_function(field, params.field, iso);
    extract::J1aIsosurfaceParams j1a;
    j1a.cell_size = params.resolution * field.stats().median_spacing;
    j1a.max_leaves = params.max_leaves;
    LSQSURF_ASSIGN_OR_RETURN(extract::IsosurfaceResult r,
                             extract::ExtractIsosurfaceJ1a(level_function, seeds, j1a, sub));
    const auto base = static_cast<uint32_t>(out.vertices.size());
    out.vertices.insert(out.vertices.end(), r.mesh.vertices.begin(), r.mesh.vertices.end());
    out.normals.insert(out.normals.end(), r.mesh.normals.begin(), r.mesh.normals.end());
    for (core::Triangle t : r.mesh.faces) out.faces.push_back({t[0] + base, t[1] + base, t[2] + base});
    level.values.resize(out.vertices.size(), static_cast<float>(iso));
  }
  if (params.iso_values.size() > 1) out.vertex_attributes.push_back(std::move(level));
  if (params.color_field >= 0) {
    core::ScalarAttribute color{field.field_names()[params.color_field], std::vector<float>(out.vertices.size())};
    LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
        out.vertices.size(), 1024,
        [&](size_t begin, size_t end) {
          for (size_t v = begin; v < end; ++v) {
            color.values[v] =
                static_cast<float>(field.Evaluate(out.vertices[v].cast<double>(), params.color_field).value);
          }
        },
        &ctx));
    out.vertex_attributes.push_back(std::move(color));
  }
  return out;
}

}  // namespace lsqsurf::volume
