#include "worker/jobs/volume_job.h"

#include <cmath>
#include <limits>
#include <random>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_header.h"
#include "worker/io/volume_codec.h"
#include "worker/jobs/surface_job.h"
#include "worker/volume/volume_isosurface.h"

namespace lsqsurf::jobs {
namespace {

constexpr char kMeshArtifact[] = "mesh.drc";
// Isosurfaces one job extracts at most: each is a full extraction.
constexpr int kMaxIsoValues = 16;
constexpr double kAnyNumber = std::numeric_limits<double>::infinity();

const core::ParamTable<VolumeJobParams>& VolumeJobParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<VolumeJobParams>();
    t->Text<&VolumeJobParams::field>("field", "the scalar field to reconstruct (required)")
        .RealList<&VolumeJobParams::iso>("iso", kMaxIsoValues, -kAnyNumber, kAnyNumber, "",
                                         "iso-values of the isosurfaces, each within the values the field takes "
                                         "at the vertices; none = no isosurface")
        .Text<&VolumeJobParams::color_by>("color_by", "a second field sampled on the isosurface, to colour by")
        .Real<&VolumeJobParams::resolution>("resolution", 0.05, 2, "",
                                            "finest extraction cube edge, share of the median vertex spacing")
        .Include(&VolumeJobParams::fit, volume::VolumeFieldParamTable())
        .AddRule([](const VolumeJobParams& p) {
          if (p.field.empty()) return absl::InvalidArgumentError("name the scalar field to reconstruct (field=NAME)");
          return absl::OkStatus();
        });
    return t;
  }();
  return *table;
}

// Decodes the uploads into a volume (not yet validated).
absl::StatusOr<volume::VolumeMesh> DecodeVolume(const Uploads& uploads, const InputLimits& limits) {
  auto it = uploads.find(kInputUpload);
  if (it == uploads.end() || it->second.empty()) {
    return absl::InvalidArgumentError("no vertices were uploaded (input: a Draco point cloud with the fields)");
  }
  volume::VolumeMesh mesh;
  if (absl::Status s = io::DecodeVolumeVertices(it->second, mesh); !s.ok()) {
    return core::WithContext("input", s);
  }
  if (auto cells = uploads.find(kCellsUpload); cells != uploads.end() && !cells->second.empty()) {
    if (auto claim = io::ReadDracoClaim(it->second); claim.ok() && claim->reorders_points) {
      return absl::InvalidArgumentError(
          "input: the vertices are a Draco point cloud coded with the KD-tree method, which does not keep their "
          "order, and the cells refer to them by index; code them with the sequential method (Draco's "
          "POINT_CLOUD_SEQUENTIAL_ENCODING, or encoding speed 10), as lsqsurf volume does");
    }
    if (absl::Status s = io::DecodeCellStream(
            cells->second, limits.max_cells,
            limits.max_inflated_bytes > 0 ? static_cast<uint64_t>(limits.max_inflated_bytes) : UINT64_MAX, mesh);
        !s.ok()) {
      return absl::Status(s.code(), core::StrCat("cells: ", s.message()));
    }
  }
  return mesh;
}

// Every iso-value within the values the field takes at the vertices: one outside would extract
// nothing, so it is refused now rather than found empty after the fit.
absl::Status CheckIsoValues(const VolumeJobParams& p, const volume::VolumeMesh& mesh) {
  const std::vector<double>& levels = p.iso;
  const volume::VertexField* field = mesh.FindField(p.field);
  if (levels.empty() || field == nullptr) return absl::OkStatus();
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (float v : field->values) {
    if (!std::isfinite(v)) continue;
    lo = std::min<double>(lo, v);
    hi = std::max<double>(hi, v);
  }
  for (double level : levels) {
    if (level < lo || level > hi) {
      return absl::InvalidArgumentError(core::StrCat("iso: ", level, " lies outside the values of '", p.field,
                                                     "' at the vertices, [", lo, ", ", hi,
                                                     "]; no isosurface would be found there"));
    }
  }
  return absl::OkStatus();
}

// An upload made fit for the engine, with what that took.
struct RepairedVolume {
  volume::VolumeMesh mesh;
  volume::VolumeRepairs repairs;
};

void AddRepairStatistics(const volume::VolumeRepairs& r, Statistics& statistics) {
  const std::array<int64_t, 6> counts = core::RepairCounts(r);
  for (size_t k = 0; k < counts.size(); ++k) {
    statistics.emplace_back(std::string(core::kVolumeRepairStatistics[k]), static_cast<double>(counts[k]));
  }
}

class VolumeKind final : public TypedJobKind<VolumeJobParams, RepairedVolume> {
 public:
  std::string_view name() const override { return "volume"; }

  std::vector<MethodInfo> Methods() const override {
    return {{"volume",
             "Anisotropic iaMLS reconstruction of a scalar field on a volume mesh or point set (seed section 5); "
             "isosurfaces with normals from the reconstructed gradient",
             core::ParamSet(VolumeJobParamTable()),
             {"iso"},
             {kInputUpload, kCellsUpload}}};
  }

  absl::StatusOr<Checked> Decode(const JobSpec&, const VolumeJobParams& params, const Uploads& uploads,
                                 const InputLimits& limits) const override {
    const VolumeJobParams* p = &params;
    LSQSURF_ASSIGN_OR_RETURN(volume::VolumeMesh mesh, DecodeVolume(uploads, limits));
    LSQSURF_RETURN_IF_ERROR(volume::CheckVolumeStructure(mesh, {limits.max_points, limits.max_cells}));
    LSQSURF_ASSIGN_OR_RETURN(volume::VolumeRepairs repairs, volume::RepairVolumeMesh(mesh));
    LSQSURF_RETURN_IF_ERROR(volume::ValidateVolumeMesh(mesh, {limits.max_points, limits.max_cells}));
    if (static_cast<int64_t>(mesh.vertex_count()) < limits.min_points) {
      return absl::InvalidArgumentError(core::StrCat("the volume has only ", mesh.vertex_count(),
                                                     " vertices; at least ", limits.min_points, " are needed"));
    }
    for (const std::string* name : {&p->field, &p->color_by}) {
      if (name->empty()) continue;
      const volume::VertexField* f = mesh.FindField(*name);
      if (f == nullptr || f->components != 1) {
        return absl::InvalidArgumentError(
            core::StrCat("the upload has no scalar field '", *name, "'; its fields: ", volume::DescribeFields(mesh)));
      }
    }
    LSQSURF_RETURN_IF_ERROR(CheckIsoValues(*p, mesh));
    const auto vertices = static_cast<int64_t>(mesh.vertex_count());
    return Checked{vertices, {std::move(mesh), repairs}, {}};
  }

  absl::StatusOr<Statistics> RunDecoded(const JobSpec& spec, const VolumeJobParams&, RepairedVolume input,
                                        RunEnvironment& env) const override {
    LSQSURF_ASSIGN_OR_RETURN(VolumeResult result,
                             ReconstructVolume(spec.params, input.mesh, env.context, env.memory_bytes));
    AddRepairStatistics(input.repairs, result.statistics);
    if (!result.mesh.empty()) {
      LSQSURF_ASSIGN_OR_RETURN(std::string encoded, EncodeResultMesh(result.mesh, spec.mesh_position_bits,
                                                                     &result.statistics, &env.context));
      LSQSURF_RETURN_IF_ERROR(env.sink.Write(kMeshArtifact, encoded));
    }
    env.context.ReportProgress("keeping the field", 0.99);
    LSQSURF_RETURN_IF_ERROR(env.sink.Write(kVolumeFieldArtifact, volume::SerializeVolumeField(*result.field)));
    return result.statistics;
  }
};

}  // namespace

absl::StatusOr<VolumeResult> ReconstructVolume(const core::ParamSet& params, const volume::VolumeMesh& mesh,
                                               core::JobContext& ctx, int64_t memory_bytes) {
  const auto* p = params.As<VolumeJobParams>();
  if (p == nullptr) return absl::InternalError("not volume parameters");
  std::vector<std::string> names = {p->field};
  if (!p->color_by.empty() && p->color_by != p->field) names.push_back(p->color_by);
  const std::vector<double>& levels = p->iso;
  core::SubContext fit_ctx(ctx, "reconstructing the field", 0.0, levels.empty() ? 1.0 : 0.6);
  LSQSURF_ASSIGN_OR_RETURN(std::unique_ptr<volume::VolumeField> field,
                           volume::BuildVolumeField(mesh, names, p->fit, fit_ctx));
  const volume::VolumeFieldStats& st = field->stats();
  VolumeResult result;
  result.statistics = {{"vertices", static_cast<double>(mesh.vertex_count())},
                       {"cells", static_cast<double>(mesh.cell_count())},
                       {"epsilon", st.epsilon},
                       {"iterations", st.iterations},
                       {"epsilon_chosen_by_cross_validation", st.chosen_by_cross_validation ? 1.0 : 0.0},
                       {"cross_validation_rms", st.cross_validation_rms},
                       {"cross_validation_points", st.cross_validation_points},
                       {"spectral_radius", st.spectral_radius},
                       {"kernels_per_vertex", st.kernels_per_vertex},
                       {"median_spacing", st.median_spacing},
                       {"widened_stars", static_cast<double>(st.widened_stars)},
                       {"field_seconds", st.seconds}};
  if (levels.empty()) {
    result.field = std::move(field);
    return result;
  }
  core::SubContext iso_ctx(ctx, "extracting isosurfaces", 0.6, 1.0);
  volume::VolumeIsosurfaceParams iso;
  iso.iso_values = levels;
  iso.resolution = p->resolution;
  iso.max_leaves = LeavesWithin(memory_bytes, iso.max_leaves);
  iso.color_field = p->color_by.empty() ? -1 : field->FieldIndex(p->color_by);
  LSQSURF_ASSIGN_OR_RETURN(result.mesh, volume::ExtractVolumeIsosurface(*field, iso, iso_ctx));
  result.statistics.emplace_back("triangles", static_cast<double>(result.mesh.faces.size()));
  result.field = std::move(field);
  return result;
}

absl::StatusOr<SampledVolume> SampleVolumeForPicture(const volume::VolumeField& field, int resolution,
                                                     int64_t max_bytes, const core::JobContext* ctx) {
  SampledVolume out;
  render::VolumeGrid& g = out.grid;
  const core::Box3& box = field.bounds();
  const double h = std::max(box.sizes().maxCoeff(), 1e-30) / (resolution - 1);
  for (int a = 0; a < 3; ++a) g.dims[a] = std::max(2, static_cast<int>(std::ceil(box.sizes()[a] / h)) + 1);
  g.origin = box.min();
  g.spacing = core::Vec3d::Constant(h);
  const size_t count = static_cast<size_t>(g.dims[0]) * g.dims[1] * g.dims[2];
  if (const int64_t bytes = static_cast<int64_t>(count * kPictureGridBytesPerPoint); bytes > max_bytes) {
    return absl::ResourceExhaustedError(core::StrCat("a volume picture at resolution ", resolution, " needs a ",
                                                     g.dims[0], "x", g.dims[1], "x", g.dims[2], " grid of ",
                                                     bytes >> 20, " MiB; this server allows ", max_bytes >> 20,
                                                     " MiB (lsqsurfd --max-render-mib): ask for a lower resolution"));
  }
  g.values.resize(count);
  g.gradients.resize(count);
  // One z-slab of points at a time: the grid itself is all that grows with the resolution.
  const size_t slab = static_cast<size_t>(g.dims[0]) * g.dims[1];
  std::vector<core::Vec3d> xs(slab);
  std::vector<volume::VolumeField::Sample> samples(slab);
  for (int k = 0; k < g.dims[2]; ++k) {
    for (int j = 0; j < g.dims[1]; ++j) {
      for (int i = 0; i < g.dims[0]; ++i)
        xs[static_cast<size_t>(j) * g.dims[0] + i] = g.origin + h * core::Vec3d(i, j, k);
    }
    LSQSURF_RETURN_IF_ERROR(field.EvaluateBatch(xs, 0, samples, ctx));
    for (size_t s = 0; s < slab; ++s) {
      const size_t i = static_cast<size_t>(k) * slab + s;
      const bool inside = std::isfinite(samples[s].value) && field.InDomain(xs[s], samples[s].weight);
      g.values[i] = inside ? static_cast<float>(samples[s].value) : std::numeric_limits<float>::quiet_NaN();
      g.gradients[i] = samples[s].gradient.cast<float>();
    }
  }
  // The grid's error where both it and the field are defined.
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> unit(0, 1);
  double sum = 0;
  int counted = 0;
  for (int tries = 0; tries < 20'000 && counted < 2'000; ++tries) {
    const core::Vec3d x = box.min() + core::Vec3d(unit(rng), unit(rng), unit(rng)).cwiseProduct(box.sizes());
    const double cached = render::GridValue(g, x);
    if (!std::isfinite(cached)) continue;
    const double exact = field.Evaluate(x, 0).value;
    sum += (cached - exact) * (cached - exact);
    out.max_error = std::max(out.max_error, std::abs(cached - exact));
    ++counted;
  }
  out.rms_error = counted > 0 ? std::sqrt(sum / counted) : 0.0;
  return out;
}

const JobKind& VolumeJobKind() {
  static const VolumeKind kind;
  return kind;
}

absl::StatusOr<VolumePicture> VolumePictures::Draw(const std::string& job_id, std::string_view bytes,
                                                   const render::RenderParams& params, render::SharedRenderer& renderer,
                                                   const core::JobContext* ctx) {
  const std::string key = core::StrCat(job_id, "/", params.volume_resolution);
  std::shared_ptr<const SampledVolume> sampled;
  {
    std::lock_guard lock(mutex_);
    if (key_ == key) sampled = grid_;
  }
  if (sampled == nullptr) {
    LSQSURF_ASSIGN_OR_RETURN(std::unique_ptr<volume::VolumeField> field, volume::DeserializeVolumeField(bytes));
    LSQSURF_ASSIGN_OR_RETURN(SampledVolume grid,
                             SampleVolumeForPicture(*field, params.volume_resolution, max_grid_bytes_, ctx));
    sampled = std::make_shared<const SampledVolume>(std::move(grid));
    std::lock_guard lock(mutex_);
    key_ = key;
    grid_ = sampled;
  }
  // The GL's shader on a GPU; on Mesa's software rasterizer (or without a GL) the C++ ray
  // caster, which draws the same picture twice as fast there (measured: 0.24 s against 0.53 s
  // for 512² frames of the 384k-tetrahedra Marschner–Lobb mesh).
  VolumePicture picture;
  auto gl = renderer.Get();
  const bool gpu = gl.ok() && (*gl)->description().find("llvmpipe") == std::string::npos &&
                   (*gl)->description().find("softpipe") == std::string::npos;
  auto image = gpu ? (*gl)->RenderVolume(sampled->grid, params, &picture.info)
                   : render::RaycastVolume(sampled->grid, params, &picture.info);
  if (!image.ok()) return image.status();
  LSQSURF_ASSIGN_OR_RETURN(picture.png, render::EncodePng(*image));
  picture.grid_rms_error = sampled->rms_error;
  picture.grid_max_error = sampled->max_error;
  return picture;
}

}  // namespace lsqsurf::jobs
