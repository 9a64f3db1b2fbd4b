#include "worker/jobs/probe_job.h"

#include <fmt/format.h>

#include <charconv>
#include <chrono>
#include <cmath>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/volume_job.h"
#include "worker/volume/volume_field.h"

namespace lsqsurf::jobs {
namespace {

using core::Vec3d;

// The grid's dimensions; {} for an empty text. Errors: kInvalidArgument.
absl::StatusOr<std::array<int64_t, 3>> ParseGrid(std::string_view text) {
  std::array<int64_t, 3> d{};
  if (text.empty()) return d;
  size_t pos = 0;
  for (int a = 0; a < 3; ++a) {
    const size_t end = a < 2 ? text.find('x', pos) : text.size();
    if (end == std::string_view::npos) break;
    auto [p, ec] = std::from_chars(text.data() + pos, text.data() + end, d[a]);
    if (ec != std::errc() || p != text.data() + end || d[a] < 2 || d[a] > 4096) {
      return absl::InvalidArgumentError(
          core::StrCat("grid '", text, "': expected NXxNYxNZ with every count within [2, 4096], e.g. 64x64x64"));
    }
    pos = end + 1;
  }
  if (d[2] == 0) {
    return absl::InvalidArgumentError(core::StrCat("grid '", text, "': expected NXxNYxNZ, e.g. 64x64x64"));
  }
  return d;
}

const core::ParamTable<ProbeJobParams>& ProbeJobParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<ProbeJobParams>();
    t->Text<&ProbeJobParams::source>("source", "id of a succeeded volume job (required)")
        .Text<&ProbeJobParams::field>("field", "one of its fields; empty = its first")
        .Text<&ProbeJobParams::grid>("grid",
                                     "NXxNYxNZ: resample on a grid over the field's box (field.vti); "
                                     "empty = the uploaded points (values.csv)")
        .AddRule([](const ProbeJobParams& p) {
          if (p.source.empty()) return absl::InvalidArgumentError("name the volume job to probe (source=ID)");
          return ParseGrid(p.grid).status();
        });
    return t;
  }();
  return *table;
}

absl::StatusOr<std::vector<Vec3d>> DecodePoints(const Uploads& uploads, int64_t max_points) {
  auto it = uploads.find(kInputUpload);
  if (it == uploads.end() || it->second.empty()) {
    return absl::InvalidArgumentError("no points were uploaded (input: a Draco point cloud), and no grid was given");
  }
  auto cloud = io::DecodeDracoPointCloud(it->second, {.max_points = max_points});
  if (!cloud.ok()) return core::WithContext("input", cloud.status());
  std::vector<Vec3d> out;
  out.reserve(cloud->size());
  for (size_t i = 0; i < cloud->size(); ++i) {
    if (!cloud->positions[i].allFinite()) {
      return absl::InvalidArgumentError(core::StrCat("point ", i, " has a NaN or infinite coordinate"));
    }
    out.push_back(cloud->positions[i].cast<double>());
  }
  return out;
}

std::string ValuesCsv(std::span<const Vec3d> xs, std::span<const volume::VolumeField::Sample> s,
                      const std::vector<char>& inside) {
  std::string out = "x,y,z,value,gx,gy,gz\n";
  for (size_t i = 0; i < xs.size(); ++i) {
    // The points arrive as floats: their shortest float form is the exact input.
    const Eigen::Vector3f x = xs[i].cast<float>();
    out += fmt::format("{},{},{}", x.x(), x.y(), x.z());
    out += inside[i]
               ? fmt::format(",{},{},{},{}\n", s[i].value, s[i].gradient.x(), s[i].gradient.y(), s[i].gradient.z())
               : std::string(",,,,\n");
  }
  return out;
}

std::string ImageVti(const std::array<int64_t, 3>& d, const Vec3d& origin, const Vec3d& spacing,
                     const std::string& name, std::span<const volume::VolumeField::Sample> s,
                     const std::vector<char>& inside) {
  const std::string extent = fmt::format("0 {} 0 {} 0 {}", d[0] - 1, d[1] - 1, d[2] - 1);
  std::string out = fmt::format(
      "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
      "<ImageData WholeExtent=\"{}\" Origin=\"{} {} {}\" Spacing=\"{} {} {}\">\n<Piece Extent=\"{}\">\n"
      "<PointData Scalars=\"{}\" Vectors=\"gradient\">\n<DataArray type=\"Float32\" Name=\"{}\" format=\"ascii\">\n",
      extent, origin.x(), origin.y(), origin.z(), spacing.x(), spacing.y(), spacing.z(), extent, name, name);
  for (size_t i = 0; i < s.size(); ++i)
    out += inside[i] ? fmt::format("{}\n", static_cast<float>(s[i].value)) : "nan\n";
  out += "</DataArray>\n<DataArray type=\"Float32\" Name=\"gradient\" NumberOfComponents=\"3\" format=\"ascii\">\n";
  for (size_t i = 0; i < s.size(); ++i) {
    const Eigen::Vector3f g = s[i].gradient.cast<float>();
    out += inside[i] ? fmt::format("{} {} {}\n", g.x(), g.y(), g.z()) : "nan nan nan\n";
  }
  out += "</DataArray>\n<DataArray type=\"UInt8\" Name=\"inside\" format=\"ascii\">\n";
  for (char c : inside) out += c ? "1\n" : "0\n";
  out += "</DataArray>\n</PointData>\n</Piece>\n</ImageData>\n</VTKFile>\n";
  return out;
}

// A probe holds per point its position, its sample (value, gradient, weight) and its line of the
// output text: 24 + 40 + up to 80 bytes, and the text once more as it is written.
MemoryEstimate ProbeMemory(int64_t points) {
  return {points * 224, "probe fewer points or a coarser grid, in parts if need be"};
}

class ProbeKind final : public TypedJobKind<ProbeJobParams, std::vector<Vec3d>> {
 public:
  std::string_view name() const override { return "probe"; }

  std::vector<MethodInfo> Methods() const override {
    return {{"probe",
             "Values and gradients of a finished volume job's field at uploaded points (values.csv) or on a "
             "regular grid (field.vti), from its kept precomputation",
             core::ParamSet(ProbeJobParamTable()),
             {},
             {kInputUpload}}};
  }

  std::vector<std::string> Referenced(const ProbeJobParams& p) const override { return {p.source}; }

  // The input is the uploaded points; empty for a grid, which the run makes from the field's bounds.
  absl::StatusOr<Checked> Decode(const JobSpec&, const ProbeJobParams& params, const Uploads& uploads,
                                 const InputLimits& limits) const override {
    const ProbeJobParams* p = &params;
    LSQSURF_ASSIGN_OR_RETURN(auto grid, ParseGrid(p->grid));
    const int64_t count = p->grid.empty() ? 0 : grid[0] * grid[1] * grid[2];
    if (p->grid.empty()) {
      LSQSURF_ASSIGN_OR_RETURN(std::vector<Vec3d> points, DecodePoints(uploads, limits.max_points));
      if (static_cast<int64_t>(points.size()) > limits.max_points) {
        return absl::ResourceExhaustedError(
            core::StrCat(points.size(), " probe points; this server accepts at most ", limits.max_points));
      }
      const auto n = static_cast<int64_t>(points.size());
      return Checked{n, std::move(points), ProbeMemory(n)};
    }
    if (count > limits.max_points) {
      return absl::ResourceExhaustedError(
          core::StrCat("a ", p->grid, " grid has ", count, " points; this server accepts at most ", limits.max_points));
    }
    return Checked{count, {}, ProbeMemory(count)};
  }

  absl::StatusOr<Statistics> RunDecoded(const JobSpec&, const ProbeJobParams& params, std::vector<Vec3d> points,
                                        RunEnvironment& env) const override {
    const ProbeJobParams* p = &params;
    env.context.ReportProgress("reading the field", 0.0);
    auto stored = env.read_result ? env.read_result(p->source, kVolumeFieldArtifact)
                                  : absl::StatusOr<std::string>(absl::UnavailableError("no job store"));
    if (!stored.ok()) {
      return absl::FailedPreconditionError(
          core::StrCat("source job ", p->source, " has no kept volume field: ", stored.status().message()));
    }
    LSQSURF_ASSIGN_OR_RETURN(std::unique_ptr<volume::VolumeField> field, volume::DeserializeVolumeField(*stored));
    const int index = p->field.empty() ? 0 : field->FieldIndex(p->field);
    if (index < 0) {
      std::string names;
      for (const auto& n : field->field_names()) core::StrAppend(&names, names.empty() ? "" : ", ", n);
      return absl::InvalidArgumentError(
          core::StrCat("job ", p->source, " has no field '", p->field, "'; its fields: ", names));
    }
    LSQSURF_ASSIGN_OR_RETURN(auto grid, ParseGrid(p->grid));
    std::vector<Vec3d> xs = std::move(points);
    Vec3d origin = field->bounds().min(), spacing = Vec3d::Zero();
    if (!p->grid.empty()) {
      for (int a = 0; a < 3; ++a) spacing[a] = field->bounds().sizes()[a] / static_cast<double>(grid[a] - 1);
      xs.reserve(static_cast<size_t>(grid[0] * grid[1] * grid[2]));
      for (int64_t k = 0; k < grid[2]; ++k) {
        for (int64_t j = 0; j < grid[1]; ++j) {
          for (int64_t i = 0; i < grid[0]; ++i) {
            xs.push_back(
                origin +
                Vec3d(static_cast<double>(i), static_cast<double>(j), static_cast<double>(k)).cwiseProduct(spacing));
          }
        }
      }
    }
    const auto start = std::chrono::steady_clock::now();
    std::vector<volume::VolumeField::Sample> samples(xs.size());
    core::SubContext eval_ctx(env.context, "evaluating", 0.05, 0.9);
    LSQSURF_RETURN_IF_ERROR(field->EvaluateBatch(xs, index, samples, &eval_ctx));
    std::vector<char> inside(xs.size());
    int64_t inside_count = 0;
    for (size_t i = 0; i < xs.size(); ++i) {
      inside[i] = std::isfinite(samples[i].value) && field->InDomain(xs[i], samples[i].weight);
      inside_count += inside[i];
    }
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    env.context.ReportProgress("writing", 0.9);
    if (p->grid.empty()) {
      LSQSURF_RETURN_IF_ERROR(env.sink.Write("values.csv", ValuesCsv(xs, samples, inside)));
    } else {
      LSQSURF_RETURN_IF_ERROR(
          env.sink.Write("field.vti", ImageVti(grid, origin, spacing, field->field_names()[index], samples, inside)));
    }
    return Statistics{{"points", static_cast<double>(xs.size())},
                      {"inside", static_cast<double>(inside_count)},
                      {"evaluate_seconds", seconds}};
  }
};

}  // namespace

const JobKind& ProbeJobKind() {
  static const ProbeKind kind;
  return kind;
}

}  // namespace lsqsurf::jobs
