#include "worker/jobs/engines.h"

#include <chrono>
#include <cmath>
#include <functional>

#include "worker/core/isosurface.h"
#include "worker/core/j1a_isosurface.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/normals.h"
#include "worker/core/strings.h"
#include "worker/jobs/front_job.h"
#include "worker/mls/algebraic_mls.h"
#include "worker/mls/iamls.h"
#include "worker/pu/pu.h"

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
  MethodSpec m{"iamls", "iterated approximate MLS surface (seed §4), extracted on a tetrahedral grid", {}, {}};
  m.parameters = {
      {"epsilon", p.epsilon, 0.05, 3, false, "kernel shape parameter; larger = more detail"},
      {"iterations", static_cast<double>(p.iterations), 0, 20, true, "residual-correction iterations; more = closer fit"},
      {"spacing", p.spacing, 0, 1e30, false,
       "kernel spacing h in model units; 0 = spacing_scale x mean nearest-neighbour distance"},
      {"spacing_scale", p.spacing_scale, 0.25, 8, false, "multiplier of the measured spacing"},
      {"cutoff", p.cutoff, 2, 8, false, "kernel truncation at epsilon*r = cutoff"},
      {"min_weight", p.min_weight, 0, 0.99, false,
       "ghost-sheet guard: no surface where the kernel sum is below this share of its mean at the samples"},
      {"cell_size", 1.5, 0.1, 16, false,
       "spacing of the extraction vertices, in units of h (grid edge; J1a leaves are twice as large, "
       "with vertices at their centres and face and edge midpoints)"},
      {"refine_steps", 3, 0, 20, true, "root-refinement steps per crossing edge"},
      {"extractor", 1, 0, 1, true,
       "1: J1a tetrahedra on an adaptive octree; 0: surface-following uniform Kuhn grid (a little faster)"},
  };
  for (auto& c : CommonParameters()) m.parameters.push_back(std::move(c));
  return m;
}

MethodSpec AlgebraicMethod(mls::AlgebraicFit fit) {
  mls::AlgebraicMlsParams p;
  const bool apss = fit == mls::AlgebraicFit::kApss;
  MethodSpec m{apss ? "apss" : "ramls",
               apss ? "algebraic point set surface (Guennebaud & Gross): normal-constrained sphere fits weighted by "
                      "beta, extracted on J1a tetrahedra"
                    : "robust algebraic MLS surface (seed §3): closed-form normal-driven sphere fits, extracted on J1a "
                      "tetrahedra",
               {}, {}};
  m.parameters = {
      {"spacing", p.spacing, 0, 1e30, false, "h in model units; 0 = spacing_scale x mean nearest-neighbour distance"},
      {"spacing_scale", p.spacing_scale, 0.25, 8, false, "multiplier of the measured spacing"},
      {"support_factor", p.support_factor, 1, 10, false, "support radius in units of h"},
      {"min_neighbors", static_cast<double>(p.min_neighbors), 4, 100, true,
       "no surface where fewer points carry weight"},
      {"coverage", p.coverage, 0.25, 10, false, "no surface farther than this many h from the nearest point"},
      {"cell_size", 1.0, 0.1, 16, false,
       "spacing of the extraction vertices in units of h (J1a leaves are twice as large)"},
      {"refine_steps", 3, 0, 20, true, "root-refinement steps per crossing edge"},
  };
  if (apss) {
    m.parameters.push_back({"beta", p.apss_beta, 1e-6, 1e12, false,
                            "weight of the normal term against the position term (dimensionless; large = RAMLS)"});
  }
  for (auto& c : CommonParameters()) m.parameters.push_back(std::move(c));
  return m;
}

MethodSpec PuMethod() {
  const pu::PuParams p;
  const pu::PuExtractParams e;
  MethodSpec m{"pu",
               "twofold adaptive partition-of-unity implicit (seed §2): orthogonal-polynomial fits of "
               "adaptive degree on an adaptive octree, extracted on its J1a tetrahedra",
               {}, {}};
  m.parameters = {
      {"error_threshold", p.error_threshold, 1e-6, 0.1, false,
       "largest fitting error accepted in a cell, as a share of the bounding-box diagonal; "
       "set it near the noise amplitude for noisy scans"},
      {"max_depth", static_cast<double>(p.max_depth), 1, 18, true, "octree levels below the root cube"},
      {"max_degree", static_cast<double>(p.max_degree), 0, 4, true, "highest polynomial degree of a local fit"},
      {"support_factor", p.support_factor, 0.55, 2, false, "support radius of a cell, in cell diagonals"},
      {"min_points", static_cast<double>(p.min_points), 4, 200, true,
       "the fitting ball of a sparse cell grows until it holds this many points"},
      {"max_normal_angle", p.max_normal_angle, 10, 180, false,
       "normal-cone criterion in degrees: wider cells are split (180 disables)"},
      {"coverage", p.coverage_check ? 1.0 : 0.0, 0, 1, true,
       "1: coverage criteria on (no sheets away from the data, holes stay open); 0: off"},
      {"coverage_factor", p.coverage_factor, 0.5, 20, false,
       "surface only within this many local spacings (distance to the 8th neighbour) of a data point"},
      {"orientation_check", p.orientation_check ? 1.0 : 0.0, 0, 1, true,
       "1: reject fits whose gradient opposes their points' normals"},
      {"noise_level", p.noise_level, -1, 0.1, false,
       "scan noise sigma as a share of the diagonal; -1 estimates it, 0 declares the data exact; "
       "above error_threshold the threshold becomes 3 sigma and min_points at least 80"},
      {"cell_size", e.cell_size, 0.25, 64, false,
       "smallest extraction cell at the surface, in units of the mean point spacing (rounded to an octree level); cells near the data are up to 4x larger where the fits allowed larger cells"},
      {"refine_steps", static_cast<double>(e.marching.refine_steps), 0, 20, true,
       "root-refinement steps per crossing edge"},
  };
  for (auto& c : CommonParameters()) m.parameters.push_back(std::move(c));
  m.attributes = {"depth", "degree"};  // Octree depth and polynomial degree of the fit dominating at a vertex.
  return m;
}


double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

using ParamFn = std::function<double(const char*)>;
using StatFn = std::function<void(std::string, double)>;

absl::StatusOr<core::IsosurfaceResult> RunIamls(const ParamFn& param, const core::PointCloud& cloud,
                                                core::JobContext& ctx, const StatFn& stat) {
  mls::IamlsParams ip;
  ip.epsilon = param("epsilon");
  ip.iterations = static_cast<int>(param("iterations"));
  ip.spacing = param("spacing");
  ip.spacing_scale = param("spacing_scale");
  ip.cutoff = param("cutoff");
  ip.min_weight = param("min_weight");
  auto start = std::chrono::steady_clock::now();
  core::SubContext build_ctx(ctx, "building iaMLS", 0.0, 0.3);
  auto field = mls::BuildIamls(cloud, ip, build_ctx);
  if (!field.ok()) return field.status();
  stat("fit_seconds", Seconds(start));
  stat("spacing", (*field)->spacing());
  stat("largest_eigenvalue", (*field)->stats().largest_eigenvalue);
  if (!(*field)->stats().residuals.empty()) stat("final_residual_over_h", (*field)->stats().residuals.back());

  start = std::chrono::steady_clock::now();
  core::SubContext extract_ctx(ctx, "extracting surface", 0.3, 1.0);
  const double cell_size = param("cell_size") * (*field)->spacing();
  core::MarchingOptions marching;
  marching.refine_steps = static_cast<int>(param("refine_steps"));
  absl::StatusOr<core::IsosurfaceResult> extracted;
  if (param("extractor") == 1) {
    // Same vertex spacing as the grid: a J1a leaf has vertices at half its edge.
    extracted = core::ExtractIsosurfaceJ1a(**field, cloud.positions, {2 * cell_size, 20'000'000, marching},
                                           extract_ctx);
  } else {
    extracted = core::ExtractIsosurface(**field, cloud.positions, {cell_size, 60'000'000, marching},
                                        extract_ctx);
  }
  if (extracted.ok()) stat("extract_seconds", Seconds(start));
  return extracted;
}

absl::StatusOr<core::IsosurfaceResult> RunAlgebraic(mls::AlgebraicFit fit, const ParamFn& param,
                                                    const core::PointCloud& cloud, core::JobContext& ctx,
                                                    const StatFn& stat) {
  mls::AlgebraicMlsParams ap;
  ap.fit = fit;
  ap.spacing = param("spacing");
  ap.spacing_scale = param("spacing_scale");
  ap.support_factor = param("support_factor");
  ap.min_neighbors = static_cast<int>(param("min_neighbors"));
  ap.coverage = param("coverage");
  if (fit == mls::AlgebraicFit::kApss) ap.apss_beta = param("beta");
  auto start = std::chrono::steady_clock::now();
  core::SubContext build_ctx(ctx, "indexing points", 0.0, 0.05);
  auto field = mls::BuildAlgebraicMls(cloud, ap, build_ctx);
  if (!field.ok()) return field.status();
  stat("spacing", (*field)->spacing());
  start = std::chrono::steady_clock::now();
  core::SubContext extract_ctx(ctx, "extracting surface", 0.05, 1.0);
  core::MarchingOptions marching;
  marching.refine_steps = static_cast<int>(param("refine_steps"));
  // A J1a leaf has vertices at half its edge, so leaves of twice the vertex spacing.
  const double leaf = 2 * param("cell_size") * (*field)->spacing();
  auto extracted = core::ExtractIsosurfaceJ1a(**field, cloud.positions, {leaf, 20'000'000, marching}, extract_ctx);
  if (extracted.ok()) stat("extract_seconds", Seconds(start));
  return extracted;
}

absl::StatusOr<core::IsosurfaceResult> RunPu(const ParamFn& param, const core::PointCloud& cloud,
                                             core::JobContext& ctx, const StatFn& stat) {
  pu::PuParams pp;
  pp.error_threshold = param("error_threshold");
  pp.max_depth = static_cast<int>(param("max_depth"));
  pp.max_degree = static_cast<int>(param("max_degree"));
  pp.support_factor = param("support_factor");
  pp.min_points = static_cast<int>(param("min_points"));
  pp.max_normal_angle = param("max_normal_angle");
  pp.coverage_check = param("coverage") != 0;
  pp.coverage_factor = param("coverage_factor");
  pp.orientation_check = param("orientation_check") != 0;
  pp.noise_level = param("noise_level");
  core::SubContext build_ctx(ctx, "fitting", 0.0, 0.4);
  auto field = pu::BuildPu(cloud, pp, build_ctx);
  if (!field.ok()) return field.status();
  const pu::PuStats& s = (*field)->stats();
  stat("fit_seconds", s.fit_seconds);
  stat("index_seconds", s.index_seconds);
  stat("mean_spacing", s.mean_spacing);
  stat("noise_level", s.noise_estimate);
  stat("error_threshold_used", s.error_threshold);
  stat("min_points_used", s.min_points);
  for (size_t d = 0; d < s.fits_per_degree.size(); ++d) {
    stat(core::StrCat("fits_degree_", d), static_cast<double>(s.fits_per_degree[d]));
  }
  stat("fits_quadric", static_cast<double>(s.quadric_fits));
  stat("fits_above_threshold", static_cast<double>(s.unmet_threshold));
  for (size_t d = 0; d < s.leaves_per_depth.size(); ++d) {
    if (s.leaves_per_depth[d] > 0) stat(core::StrCat("leaves_depth_", d), static_cast<double>(s.leaves_per_depth[d]));
  }
  const auto start = std::chrono::steady_clock::now();
  pu::PuExtractParams ep;
  ep.cell_size = param("cell_size");
  ep.marching.refine_steps = static_cast<int>(param("refine_steps"));
  core::SubContext extract_ctx(ctx, "extracting surface", 0.4, 1.0);
  auto extracted = pu::Extract(**field, ep, extract_ctx);
  if (extracted.ok()) {
    stat("extract_seconds", Seconds(start));
    stat("tetrahedra", static_cast<double>(extracted->stats.tetrahedra));
  }
  return extracted;
}

}  // namespace

const std::vector<MethodSpec>& SurfaceMethods() {
  static const std::vector<MethodSpec> methods = {IamlsMethod(), PuMethod(), AlgebraicMethod(mls::AlgebraicFit::kRamls),
                                                  AlgebraicMethod(mls::AlgebraicFit::kApss), TrackMethod()};
  return methods;
}

const MethodSpec* FindMethod(const std::string& name) {
  for (const auto& m : SurfaceMethods()) {
    if (m.name == name) return &m;
  }
  return nullptr;
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
  if (method == kTrackMethod) return absl::InvalidArgumentError("'track' is a front-tracking job, not a surface method");
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

  core::SubContext engine_ctx(ctx, method, normals_share, 1.0);
  absl::StatusOr<core::IsosurfaceResult> extracted =
      method == "pu"      ? RunPu(param, cloud, engine_ctx, stat)
      : method == "ramls" ? RunAlgebraic(mls::AlgebraicFit::kRamls, param, cloud, engine_ctx, stat)
      : method == "apss"  ? RunAlgebraic(mls::AlgebraicFit::kApss, param, cloud, engine_ctx, stat)
                          : RunIamls(param, cloud, engine_ctx, stat);
  if (!extracted.ok()) return extracted.status();
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
