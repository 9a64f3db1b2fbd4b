#include "worker/jobs/engines.h"

#include <chrono>
#include <cmath>

#include "worker/core/isosurface.h"
#include "worker/core/j1a_isosurface.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/normals.h"
#include "worker/core/strings.h"
#include "worker/mls/iamls.h"

namespace lsqsurf::jobs {
namespace {

std::vector<ParameterSpec> CommonParameters() {
  const core::NormalEstimationParams normals;
  return {
      {"estimate_normals", 1, 0, 1, true,
       "1: estimate normals when the cloud has none (PCA + spanning-tree orientation); "
       "0: reject clouds without normals"},
      {"normal_neighbors", static_cast<double>(normals.neighbors), 3, 128, true,
       "neighbours used to estimate normals"},
  };
}

MethodSpec IamlsMethod() {
  const mls::IamlsParams p;
  MethodSpec m{"iamls", "iterated approximate MLS surface (seed §4), extracted on a tetrahedral grid", {}};
  m.parameters = {
      {"epsilon", p.epsilon, 0.05, 3, false, "kernel shape parameter; larger = more detail"},
      {"iterations", static_cast<double>(p.iterations), 0, 20, true, "residual-correction iterations; more = closer fit"},
      {"spacing", p.spacing, 0, 1e30, false,
       "kernel spacing h in model units; 0 = spacing_scale x mean nearest-neighbour distance"},
      {"spacing_scale", p.spacing_scale, 0.25, 8, false, "multiplier of the measured spacing"},
      {"cutoff", p.cutoff, 2, 8, false, "kernel truncation at epsilon*r = cutoff"},
      {"min_weight", p.min_weight, 0, 0.99, false,
       "ghost-sheet guard: no surface where the kernel sum is below this share of its mean at the samples"},
      {"cell_size", 1.5, 0.1, 16, false, "extraction grid cell edge, in units of h"},
      {"refine_steps", 3, 0, 20, true, "root-refinement steps per crossing edge"},
      {"extractor", 0, 0, 1, true,
       "0: surface-following uniform tetrahedral grid; 1: adaptive J1a tetrahedra (finest leaf = cell_size)"},
  };
  for (auto& c : CommonParameters()) m.parameters.push_back(std::move(c));
  return m;
}

const MethodSpec* FindMethod(const std::string& name) {
  for (const auto& m : SurfaceMethods()) {
    if (m.name == name) return &m;
  }
  return nullptr;
}

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

}  // namespace

const std::vector<MethodSpec>& SurfaceMethods() {
  static const std::vector<MethodSpec> methods = {IamlsMethod()};
  return methods;
}

absl::Status ValidateRequest(const std::string& method, const ParameterMap& parameters) {
  const MethodSpec* m = FindMethod(method);
  if (m == nullptr) {
    std::string known;
    for (const auto& s : SurfaceMethods()) known += (known.empty() ? "" : ", ") + s.name;
    return absl::InvalidArgumentError(core::StrCat("unknown method '", method, "'; available: ", known));
  }
  for (const auto& [name, value] : parameters) {
    const ParameterSpec* spec = nullptr;
    for (const auto& p : m->parameters) {
      if (p.name == name) spec = &p;
    }
    if (spec == nullptr) {
      std::string valid;
      for (const auto& p : m->parameters) valid += (valid.empty() ? "" : ", ") + p.name;
      return absl::InvalidArgumentError(core::StrCat("unknown parameter '", name, "' for method ", method,
                                                     "; valid parameters: ", valid));
    }
    if (!std::isfinite(value) || value < spec->min_value || value > spec->max_value) {
      return absl::InvalidArgumentError(core::StrCat("parameter ", name, "=", value, " is out of range [",
                                                     spec->min_value, ", ", spec->max_value, "]"));
    }
    if (spec->integer && value != std::floor(value)) {
      return absl::InvalidArgumentError(core::StrCat("parameter ", name, "=", value, " must be a whole number"));
    }
  }
  return absl::OkStatus();
}

double ParameterOrDefault(const std::string& method, const ParameterMap& parameters,
                          const std::string& name) {
  if (auto it = parameters.find(name); it != parameters.end()) return it->second;
  if (const MethodSpec* m = FindMethod(method)) {
    for (const auto& p : m->parameters) {
      if (p.name == name) return p.default_value;
    }
  }
  return 0;
}

absl::StatusOr<SurfaceResult> RunSurfaceMethod(const std::string& method,
                                               const ParameterMap& parameters,
                                               core::PointCloud cloud, core::JobContext& ctx) {
  if (absl::Status s = ValidateRequest(method, parameters); !s.ok()) return s;
  auto param = [&](const char* name) { return ParameterOrDefault(method, parameters, name); };
  SurfaceResult result;
  auto stat = [&](std::string name, double value) { result.statistics.emplace_back(std::move(name), value); };
  stat("input_points", static_cast<double>(cloud.size()));

  double normals_share = 0.0;
  if (!cloud.has_normals()) {
    if (param("estimate_normals") == 0) {
      return absl::InvalidArgumentError("the cloud has no normals and estimate_normals is 0");
    }
    normals_share = 0.2;
    const auto start = std::chrono::steady_clock::now();
    core::SubContext sub(ctx, "estimating normals", 0.0, normals_share);
    core::NormalEstimationParams np;
    np.neighbors = static_cast<int>(param("normal_neighbors"));
    auto normals = core::EstimateNormals(cloud.positions, np, sub);
    if (!normals.ok()) return normals.status();
    cloud.normals = *std::move(normals);
    stat("normals_seconds", Seconds(start));
  }

  // Only iaMLS exists so far; the registry grows with the engines.
  mls::IamlsParams ip;
  ip.epsilon = param("epsilon");
  ip.iterations = static_cast<int>(param("iterations"));
  ip.spacing = param("spacing");
  ip.spacing_scale = param("spacing_scale");
  ip.cutoff = param("cutoff");
  ip.min_weight = param("min_weight");
  auto start = std::chrono::steady_clock::now();
  core::SubContext build_ctx(ctx, "building iaMLS", normals_share, normals_share + 0.3 * (1 - normals_share));
  auto field = mls::BuildIamls(cloud, ip, build_ctx);
  if (!field.ok()) return field.status();
  stat("fit_seconds", Seconds(start));
  stat("spacing", (*field)->spacing());
  stat("largest_eigenvalue", (*field)->stats().largest_eigenvalue);
  if (!(*field)->stats().residuals.empty()) stat("final_residual_over_h", (*field)->stats().residuals.back());

  start = std::chrono::steady_clock::now();
  core::SubContext extract_ctx(ctx, "extracting surface", normals_share + 0.3 * (1 - normals_share), 1.0);
  const double cell_size = param("cell_size") * (*field)->spacing();
  core::MarchingOptions marching;
  marching.refine_steps = static_cast<int>(param("refine_steps"));
  absl::StatusOr<core::IsosurfaceResult> extracted;
  if (param("extractor") == 1) {
    extracted = core::ExtractIsosurfaceJ1a(**field, cloud.positions, {cell_size, 20'000'000, marching},
                                           extract_ctx);
  } else {
    extracted = core::ExtractIsosurface(**field, cloud.positions, {cell_size, 60'000'000, marching},
                                        extract_ctx);
  }
  if (!extracted.ok()) return extracted.status();
  stat("extract_seconds", Seconds(start));
  result.mesh = std::move(extracted->mesh);
  if (result.mesh.faces.empty()) {
    return absl::FailedPreconditionError(
        "no surface was found: the points may be too sparse for the chosen spacing");
  }
  const core::MeshTopology topo = core::AnalyzeTopology(result.mesh);
  stat("triangles", static_cast<double>(topo.faces));
  stat("vertices", static_cast<double>(topo.vertices));
  stat("boundary_edges", static_cast<double>(topo.boundary_edges));
  stat("non_manifold_edges", static_cast<double>(topo.non_manifold_edges));
  stat("components", static_cast<double>(topo.components));
  stat("cells_visited", static_cast<double>(extracted->stats.cells_visited));
  return result;
}

}  // namespace lsqsurf::jobs
