// Anisotropic iaMLS volume fields; see volume_field.h for the formulas.
#include "worker/volume/volume_field.h"

#include <fmt/format.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <numbers>

#include "worker/core/binary.h"
#include "worker/core/kd_tree.h"
#include "worker/core/kernel_matrix.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/volume/kernels.h"

namespace lsqsurf::volume {
namespace {

// The iteration is refused when I − A would amplify some error component by more than this per
// step (a few steps at 1.05 are harmless; beyond it the error grows visibly).
constexpr double kMaxSpectralRadius = 1.05;
// Cross-validation: neighbourhoods, their size, the share of inner vertices held out.
constexpr int kCvRegions = 4;
constexpr size_t kCvRegionSize = 10'000;
constexpr uint32_t kCvHoldOutModulus = 25;
constexpr int kCvMaxIterations = 16;
constexpr double kCvTolerance = 1.02;

const std::array<double, 5> kEpsilonCandidates = {0.7, 0.85, 1.0, 1.2, 1.45};

using core::KernelMatrix;

// Rows of Ψ_i(x_k) for query points x_k.
// `normalized`: each row divided by its sum (Shepard normalisation of the quasi-interpolant).
absl::StatusOr<KernelMatrix> BuildMatrix(const Kernels& kernels, std::span<const Vec3f> queries, bool normalized,
                                         const core::JobContext* ctx) {
  return core::BuildKernelMatrix(
      queries.size(),
      [&](size_t k) {
        uint64_t count = 0;
        kernels.ForEach(queries[k].cast<double>(), [&](uint32_t, float, const Vec3f&) { ++count; });
        return count;
      },
      [&](size_t k, uint32_t* column, float* value) {
        size_t e = 0;
        double sum = 0;
        kernels.ForEach(queries[k].cast<double>(), [&](uint32_t i, float psi, const Vec3f&) {
          column[e] = i;
          value[e++] = psi;
          sum += psi;
        });
        if (normalized && sum > 0) {
          for (size_t q = 0; q < e; ++q) value[q] = static_cast<float>(value[q] / sum);
        }
      },
      ctx);
}

// The spectral radius of I − A by power steps: the growth rate of ‖(I − A)ᵏ v‖ over the last steps.
double SpectralRadius(const KernelMatrix& a) {
  const size_t n = a.row_start.size() - 1;
  std::vector<double> v(n), av;
  for (size_t k = 0; k < n; ++k) v[k] = std::sin(0.7 * static_cast<double>(k) + 0.3) + 0.1;
  auto norm = [&] {
    double s = 0;
    for (double x : v) s += x * x;
    return std::sqrt(s);
  };
  constexpr int kSteps = 30, kMeasured = 10;
  double log_growth = 0;
  for (int step = 0; step < kSteps; ++step) {
    const double before = norm();
    for (double& x : v) x /= before;
    a.Multiply(v, av, 1);
    for (size_t k = 0; k < n; ++k) v[k] -= av[k];
    if (step >= kSteps - kMeasured) log_growth += std::log(std::max(norm(), 1e-300));
  }
  return std::exp(log_growth / kMeasured);
}

// The linear terms of the value rows: s_k = Σ_i A_ki ∇f_i·(x_k − x_i), which the iteration
// treats as fixed (see VolumeFieldParams::linear_terms).
std::vector<double> LinearTerms(const KernelMatrix& a, std::span<const Vec3f> rows, std::span<const Vec3f> centers,
                                std::span<const Vec3f> gradients) {
  const size_t n = rows.size();
  std::vector<double> s(n, 0.0);
  (void)core::ParallelFor(n, 2048, [&](size_t begin, size_t end) {
    for (size_t k = begin; k < end; ++k) {
      double sum = 0;
      for (uint64_t e = a.row_start[k]; e < a.row_start[k + 1]; ++e) {
        const uint32_t i = a.column[e];
        sum += a.value[e] * static_cast<double>(gradients[i].dot(rows[k] - centers[i]));
      }
      s[k] = sum;
    }
  });
  return s;
}

// Richardson iteration on interleaved columns: g ← g + (f − A g − offset), `iterations` times
// (`offset`: fixed terms of the rows, same layout as f, or null).
// `residuals`, when given, receives max |f − A g − offset| of column 0 before each step and after the last.
std::vector<double> Iterate(const KernelMatrix& a, const std::vector<double>& f, const std::vector<double>* offset,
                            int columns, int iterations, std::vector<double>* residuals) {
  std::vector<double> g = f, ag;
  for (int it = 0; it <= iterations; ++it) {
    if (residuals == nullptr && it == iterations) break;
    a.Multiply(g, ag, columns);
    double worst = 0;
    for (size_t k = 0; k < f.size(); ++k) {
      const double r = f[k] - ag[k] - (offset != nullptr ? (*offset)[k] : 0.0);
      if (k % columns == 0) worst = std::max(worst, std::abs(r));
      if (it < iterations) g[k] += r;
    }
    if (residuals != nullptr) residuals->push_back(worst);
  }
  return g;
}

struct CvChoice {
  double epsilon = 0;
  int iterations = 0;
  double rms = 0;
  int points = 0;
};

// Leave-out cross-validation of (ε, iterations) on the first field; see volume_field.h.
absl::StatusOr<CvChoice> CrossValidate(std::span<const Vec3f> positions, std::span<const float> values,
                                       std::span<const Vec3f> gradients, std::span<const Sym3> metric,
                                       std::span<const float> volume, const VolumeFieldParams& p,
                                       const core::JobContext& ctx) {
  const size_t n = positions.size();
  // Neighbourhoods: the vertices nearest to a few spread-out centres (the positions are in
  // Morton order, so evenly spaced indices are spread in space).
  std::vector<uint32_t> subset;
  std::vector<char> inner(n, 0);
  if (n <= kCvRegions * kCvRegionSize) {
    subset.resize(n);
    for (size_t i = 0; i < n; ++i) subset[i] = static_cast<uint32_t>(i);
    std::fill(inner.begin(), inner.end(), 1);
  } else {
    core::KdTree tree(positions);
    std::vector<core::Neighbor> nn;
    std::vector<char> taken(n, 0);
    for (int r = 0; r < kCvRegions; ++r) {
      const size_t centre = n * (2 * r + 1) / (2 * kCvRegions);
      tree.Knn(positions[centre], kCvRegionSize, nn);
      for (size_t q = 0; q < nn.size(); ++q) {
        if (!taken[nn[q].index]) subset.push_back(nn[q].index);
        taken[nn[q].index] = 1;
        if (q < kCvRegionSize / 2) inner[nn[q].index] = 1;
      }
    }
  }
  std::vector<Vec3f> train_x, held_x, train_g;
  std::vector<Sym3> train_m;
  std::vector<float> train_v;
  std::vector<double> train_f, held_f;
  for (uint32_t i : subset) {
    if (inner[i] && (i * 2654435761u >> 8) % kCvHoldOutModulus == 0) {
      held_x.push_back(positions[i]);
      held_f.push_back(values[i]);
    } else {
      train_x.push_back(positions[i]);
      train_g.push_back(p.linear_terms ? gradients[i] : Vec3f::Zero());
      train_m.push_back(metric[i]);
      train_v.push_back(volume[i]);
      train_f.push_back(values[i]);
    }
  }
  if (held_x.size() < 10) return CvChoice{};
  // A held-out vertex's volume goes to its 8 nearest training vertices, so that the kernels
  // still cover the gap it leaves.
  {
    core::KdTree train_tree(train_x);
    std::vector<core::Neighbor> nn;
    const std::vector<float> base = train_v;
    for (size_t h = 0; h < held_x.size(); ++h) {
      train_tree.Knn(held_x[h], 8, nn);
      // The held-out vertex's own volume is not kept; its neighbours' mean stands in.
      double share = 0;
      for (const auto& q : nn) share += base[q.index];
      share /= static_cast<double>(nn.size() * nn.size());
      for (const auto& q : nn) train_v[q.index] += static_cast<float>(share);
    }
  }
  std::vector<double> epsilons(kEpsilonCandidates.begin(), kEpsilonCandidates.end());
  if (p.epsilon > 0) epsilons = {p.epsilon};
  const int max_iterations = p.iterations >= 0 ? p.iterations : kCvMaxIterations;
  struct Score {
    double epsilon;
    int iterations;
    double rms;
  };
  std::vector<Score> scores;
  for (double eps : epsilons) {
    const Kernels kernels(train_x, train_m, train_v, p, eps);
    LSQSURF_ASSIGN_OR_RETURN(KernelMatrix a, BuildMatrix(kernels, train_x, p.normalize, &ctx));
    LSQSURF_ASSIGN_OR_RETURN(KernelMatrix b, BuildMatrix(kernels, held_x, p.normalize, &ctx));
    const std::vector<double> train_s = LinearTerms(a, train_x, train_x, train_g);
    const std::vector<double> held_s = LinearTerms(b, held_x, train_x, train_g);
    std::vector<double> g = train_f, ag, pred;
    double previous_residual = 1e300;
    for (int it = 0; it <= max_iterations; ++it) {
      b.Multiply(g, pred, 1);
      double sum = 0;
      for (size_t h = 0; h < held_f.size(); ++h) {
        sum += (pred[h] + held_s[h] - held_f[h]) * (pred[h] + held_s[h] - held_f[h]);
      }
      if (p.iterations < 0 || it == p.iterations) {
        scores.push_back({eps, it, std::sqrt(sum / static_cast<double>(held_f.size()))});
      }
      a.Multiply(g, ag, 1);
      double residual = 0;
      for (size_t k = 0; k < g.size(); ++k) {
        const double r = train_f[k] - ag[k] - train_s[k];
        residual += r * r;
        g[k] += r;
      }
      // A growing residual means this ε diverges here: stop scoring it.
      if (residual > 1.5 * previous_residual) break;
      previous_residual = residual;
    }
    if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
  }
  double best = 1e300;
  for (const Score& s : scores) best = std::min(best, s.rms);
  CvChoice choice;
  choice.points = static_cast<int>(held_x.size());
  choice.epsilon = 0;
  for (const Score& s : scores) {
    if (s.rms > kCvTolerance * best) continue;
    if (s.epsilon > choice.epsilon || (s.epsilon == choice.epsilon && s.iterations < choice.iterations)) {
      choice.epsilon = s.epsilon;
      choice.iterations = s.iterations;
      choice.rms = s.rms;
    }
  }
  return choice;
}

}  // namespace

struct VolumeField::Impl {
  std::vector<Vec3f> positions;               // Morton order.
  std::vector<std::vector<float>> values;     // Per field, data values.
  std::vector<std::vector<Vec3f>> gradients;  // Per field, least-squares gradients.
  std::vector<float> spacing;                 // Mean star edge.
  std::vector<std::vector<float>> g;          // Per field, accumulated value coefficients.
  std::vector<std::vector<Vec3f>> big_g;      // Per field, accumulated gradient coefficients.
  std::unique_ptr<Kernels> kernels;
  std::vector<std::vector<KernelCoefficients>> packed;  // Per field: g_i, ∇f_i (or 0), G_i.

  void Pack(bool linear_terms) {
    packed.resize(g.size());
    for (size_t f = 0; f < g.size(); ++f) {
      packed[f].resize(g[f].size());
      for (size_t i = 0; i < g[f].size(); ++i) {
        packed[f][i] = {g[f][i], linear_terms ? gradients[f][i] : Vec3f::Zero(), big_g[f][i], 0.0f};
      }
    }
  }
};

const core::ParamTable<VolumeFieldParams>& VolumeFieldParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<VolumeFieldParams>();
    t->Real<&VolumeFieldParams::epsilon>("epsilon", 0.3, 2.5, "", "kernel shape (larger = narrower, more detail)")
        .Or(0, "chosen by cross-validation")
        .Integer<&VolumeFieldParams::iterations>("iterations", 0, 20, "", "residual-correction iterations")
        .Or(-1, "chosen by cross-validation")
        .Real<&VolumeFieldParams::spacing>("spacing", 0, 1e30, "model units",
                                           "kernel spacing H for every vertex; 0 = spacing_scale x the cube root of "
                                           "the volume each vertex stands for")
        .Real<&VolumeFieldParams::spacing_scale>("spacing_scale", 0.5, 4, "", "multiplier of the local spacing")
        .Flag<&VolumeFieldParams::anisotropic>("anisotropic",
                                               "kernels stretched like the mesh's cells (metric of each vertex's star)")
        .Real<&VolumeFieldParams::max_anisotropy>("max_anisotropy", 1, 1000, "",
                                                  "largest ratio of a kernel's axis lengths")
        .Flag<&VolumeFieldParams::normalize>("normalize",
                                             "divide by the kernel sum (exact constants on irregular meshes); "
                                             "off = the seed's plain sum")
        .Flag<&VolumeFieldParams::linear_terms>("linear_terms",
                                                "each kernel carries its vertex's value plus its gradient's linear "
                                                "term (exact linear fields on irregular meshes)")
        .Real<&VolumeFieldParams::cutoff>("cutoff", 2, 6, "", "kernel truncation at epsilon*r = cutoff")
        .Choice<&VolumeFieldParams::gradient_weights>(
            "gradient_weights",
            {{"gaussian", static_cast<int>(GradientWeights::kGaussian), "exp(-d^2/h^2), h the star's mean edge"},
             {"inverse_distance", static_cast<int>(GradientWeights::kInverseDistance), "1/d^2 (Mavriplis)"}},
            "weights of the least-squares gradients")
        .Integer<&VolumeFieldParams::neighbors>("neighbors", 6, 64, "",
                                                "nearest neighbours forming a vertex's star when there are no cells")
        .Real<&VolumeFieldParams::min_weight>("min_weight", 0.05, 1, "",
                                              "point sets: the domain is where the kernel sum reaches this value");
    return t;
  }();
  return *table;
}

absl::Status Validate(const VolumeFieldParams& params) { return VolumeFieldParamTable().Validate(params); }

VolumeField::VolumeField(Description description, std::shared_ptr<const Impl> impl,
                         std::unique_ptr<CellLocator> locator)
    : description_(std::move(description)), impl_(std::move(impl)), locator_(std::move(locator)) {}

VolumeField::Sample VolumeField::ToSample(const KernelSum& sum) const {
  Sample out;
  if (sum.weight == 0) return out;
  out.value = description_.normalize ? sum.value / sum.weight : sum.value;
  out.gradient = description_.normalize ? Vec3d(sum.gradient / sum.weight) : sum.gradient;
  out.weight = sum.weight;
  return out;
}

VolumeField::Sample VolumeField::Evaluate(const Vec3d& x, int field) const {
  return ToSample(impl_->kernels->Sum(x, impl_->packed[field]));
}

bool VolumeField::InDomain(const Vec3d& x, double weight) const {
  if (locator_ != nullptr) return locator_->Contains(x);
  return weight >= description_.min_weight;
}

absl::Status VolumeField::EvaluateBatch(std::span<const Vec3d> xs, int field, std::span<Sample> out,
                                        const core::JobContext* ctx) const {
  std::vector<KernelSum> sums(xs.size());
  LSQSURF_RETURN_IF_ERROR(impl_->kernels->SumBatch(xs, impl_->packed[field], sums, ctx));
  for (size_t k = 0; k < xs.size(); ++k) out[k] = ToSample(sums[k]);
  return absl::OkStatus();
}

int VolumeField::FieldIndex(std::string_view name) const {
  for (size_t f = 0; f < description_.field_names.size(); ++f) {
    if (description_.field_names[f] == name) return static_cast<int>(f);
  }
  return -1;
}

std::span<const Vec3f> VolumeField::positions() const { return impl_->positions; }
std::span<const float> VolumeField::data_values(int field) const { return impl_->values[field]; }
std::span<const Vec3f> VolumeField::data_gradients(int field) const { return impl_->gradients[field]; }
std::span<const float> VolumeField::data_spacing() const { return impl_->spacing; }

namespace {

// g and G of field f by the iteration, on four interleaved columns: the value and the three
// gradient components.
void AccumulateCoefficients(const KernelMatrix& a, VolumeField::Impl& impl, size_t f, bool linear_terms, int iterations,
                            std::vector<double>* residuals) {
  const size_t n = impl.positions.size();
  std::vector<double> data(n * 4);
  for (size_t k = 0; k < n; ++k) {
    data[k * 4] = impl.values[f][k];
    for (int c = 0; c < 3; ++c) data[k * 4 + 1 + c] = impl.gradients[f][k][c];
  }
  std::vector<double> offset;
  if (linear_terms) {
    const std::vector<double> s = LinearTerms(a, impl.positions, impl.positions, impl.gradients[f]);
    offset.assign(n * 4, 0.0);
    for (size_t k = 0; k < n; ++k) offset[k * 4] = s[k];
  }
  const std::vector<double> coef = Iterate(a, data, linear_terms ? &offset : nullptr, 4, iterations, residuals);
  impl.g[f].resize(n);
  impl.big_g[f].resize(n);
  for (size_t k = 0; k < n; ++k) {
    impl.g[f][k] = static_cast<float>(coef[k * 4]);
    impl.big_g[f][k] = Vec3f(static_cast<float>(coef[k * 4 + 1]), static_cast<float>(coef[k * 4 + 2]),
                             static_cast<float>(coef[k * 4 + 3]));
  }
}

}  // namespace

absl::StatusOr<std::unique_ptr<VolumeField>> BuildVolumeField(const VolumeMesh& mesh,
                                                              std::span<const std::string> field_names,
                                                              const VolumeFieldParams& params, core::JobContext& ctx) {
  const auto start = std::chrono::steady_clock::now();
  LSQSURF_RETURN_IF_ERROR(Validate(params));
  if (field_names.empty()) return absl::InvalidArgumentError("name at least one field to reconstruct");
  std::vector<const VertexField*> fields;
  for (const std::string& name : field_names) {
    const VertexField* f = mesh.FindField(name);
    if (f == nullptr || f->components != 1) {
      return absl::InvalidArgumentError(
          core::StrCat("the volume has no scalar field '", name, "'; its fields: ", DescribeFields(mesh)));
    }
    fields.push_back(f);
  }
  core::SubContext star_ctx(ctx, "gradients and metrics", 0.0, 0.2);
  StarParams star_params;
  star_params.weights = params.gradient_weights;
  star_params.neighbors = params.neighbors;
  star_params.max_anisotropy = params.max_anisotropy;
  LSQSURF_ASSIGN_OR_RETURN(VertexStars stars, AnalyseStars(mesh, fields, star_params, star_ctx));

  VolumeField::Description description;
  description.field_names.assign(field_names.begin(), field_names.end());
  description.min_weight = params.min_weight;
  description.normalize = params.normalize;
  description.linear_terms = params.linear_terms;
  std::unique_ptr<CellLocator> locator;
  if (mesh.has_cells()) locator = std::make_unique<CellLocator>(mesh);
  VolumeFieldStats& st = description.stats;
  st.mean_star_size = stars.mean_star_size;
  st.widened_stars = stars.widened_stars;
  st.singular_stars = stars.singular_stars;

  // Morton order: kernels close in space are close in memory.
  const size_t n = mesh.vertex_count();
  const std::vector<uint32_t> order = core::MortonOrder(mesh.positions);
  auto impl = std::make_shared<VolumeField::Impl>();
  std::vector<Sym3> metric(n);
  std::vector<float> volume(n);
  impl->positions.resize(n);
  impl->spacing.resize(n);
  impl->values.assign(fields.size(), std::vector<float>(n));
  impl->gradients.assign(fields.size(), std::vector<Vec3f>(n));
  for (size_t r = 0; r < n; ++r) {
    const uint32_t i = order[r];
    impl->positions[r] = mesh.positions[i];
    description.bounds.extend(mesh.positions[i].cast<double>());
    metric[r] = stars.metric[i];
    // A vertex no cell uses still needs a volume: its spacing cubed.
    volume[r] = stars.volume[i] > 0 ? stars.volume[i] : std::pow(stars.mean_edge[i], 3.0f);
    impl->spacing[r] = stars.mean_edge[i];
    for (size_t f = 0; f < fields.size(); ++f) {
      impl->values[f][r] = fields[f]->values[i];
      impl->gradients[f][r] = stars.gradients[f][i];
    }
  }
  {
    std::vector<float> sorted = impl->spacing;
    std::nth_element(sorted.begin(), sorted.begin() + static_cast<int64_t>(n / 2), sorted.end());
    st.median_spacing = sorted[n / 2];
  }

  core::SubContext cv_ctx(ctx, "choosing epsilon and iterations", 0.2, 0.5);
  double eps = params.epsilon;
  int iterations = params.iterations;
  if (eps == 0 || iterations < 0) {
    LSQSURF_ASSIGN_OR_RETURN(CvChoice choice, CrossValidate(impl->positions, impl->values[0], impl->gradients[0],
                                                            metric, volume, params, cv_ctx));
    st.chosen_by_cross_validation = true;
    st.cross_validation_rms = choice.rms;
    st.cross_validation_points = choice.points;
    // Too few vertices to hold any out: the middle of the candidates.
    if (eps == 0) eps = choice.epsilon > 0 ? choice.epsilon : 1.0;
    if (iterations < 0) iterations = choice.epsilon > 0 ? choice.iterations : 3;
  }
  cv_ctx.Report(1.0);

  core::SubContext fit_ctx(ctx, "iterating", 0.5, 1.0);
  impl->kernels = std::make_unique<Kernels>(impl->positions, metric, volume, params, eps);
  LSQSURF_ASSIGN_OR_RETURN(KernelMatrix a, BuildMatrix(*impl->kernels, impl->positions, params.normalize, &ctx));
  st.kernels_per_vertex = static_cast<double>(a.row_start[n]) / static_cast<double>(n);
  fit_ctx.Report(0.3);
  if (iterations > 0) {
    st.spectral_radius = SpectralRadius(a);
    if (st.spectral_radius > kMaxSpectralRadius) {
      return absl::InvalidArgumentError(fmt::format(
          "epsilon={:.3g} with {} iterations diverges on this mesh (spectral radius of I - A {:.3g}, must stay below "
          "{}); use a smaller epsilon, iterations=0, or epsilon=0 to let the server choose",
          eps, iterations, st.spectral_radius, kMaxSpectralRadius));
    }
  }
  fit_ctx.Report(0.6);
  impl->g.resize(fields.size());
  impl->big_g.resize(fields.size());
  for (size_t f = 0; f < fields.size(); ++f) {
    AccumulateCoefficients(a, *impl, f, params.linear_terms, iterations, f == 0 ? &st.residuals : nullptr);
    if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
  }
  st.epsilon = eps;
  st.iterations = iterations;
  st.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  impl->Pack(params.linear_terms);
  return std::make_unique<VolumeField>(std::move(description), std::move(impl), std::move(locator));
}

constexpr std::string_view kFieldMagic = "LQVF0001";

bool IsStoredVolumeField(std::string_view bytes) {
  return bytes.size() >= 8 + kFieldMagic.size() && bytes.substr(8, kFieldMagic.size()) == kFieldMagic;
}

std::string SerializeVolumeField(const VolumeField& field) {
  const VolumeField::Impl& m = field.impl();
  const VolumeField::Description& d = field.description();
  const VolumeFieldStats& st = d.stats;
  core::BinaryWriter w;
  w.Array<char>(std::span<const char>(kFieldMagic.data(), kFieldMagic.size()));
  w.Scalar<uint64_t>(d.field_names.size());
  for (const std::string& name : d.field_names) w.Text(name);
  w.Scalar(d.min_weight);
  w.Scalar<uint8_t>(d.normalize);
  w.Scalar<uint8_t>(d.linear_terms);
  for (double v : {st.epsilon, static_cast<double>(st.iterations), st.chosen_by_cross_validation ? 1.0 : 0.0,
                   st.cross_validation_rms, static_cast<double>(st.cross_validation_points), st.spectral_radius,
                   st.kernels_per_vertex, st.median_spacing, st.mean_star_size, st.seconds}) {
    w.Scalar(v);
  }
  w.Scalar(m.kernels->cutoff2());
  w.Array<KernelRecord>(m.kernels->records());
  w.Array<Vec3f>(m.positions);
  w.Array<float>(m.spacing);
  for (size_t f = 0; f < d.field_names.size(); ++f) {
    w.Array<float>(m.values[f]);
    w.Array<Vec3f>(m.gradients[f]);
    w.Array<float>(m.g[f]);
    w.Array<Vec3f>(m.big_g[f]);
  }
  const CellLocator* locator = field.locator();
  w.Array<Vec3f>(locator != nullptr ? locator->positions() : std::span<const Vec3f>());
  w.Array<std::array<uint32_t, 4>>(locator != nullptr ? locator->tets() : std::span<const std::array<uint32_t, 4>>());
  return w.Take();
}

absl::StatusOr<std::unique_ptr<VolumeField>> DeserializeVolumeField(std::string_view bytes) {
  auto bad = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("the stored volume field is unreadable: ", why));
  };
  core::BinaryReader r(bytes);
  std::vector<char> magic;
  if (!r.Array(magic) || std::string_view(magic.data(), magic.size()) != kFieldMagic) return bad("wrong header");
  VolumeField::Description d;
  auto impl = std::make_shared<VolumeField::Impl>();
  uint64_t fields = 0;
  if (!r.Scalar(fields) || fields == 0 || fields > 64) return bad("field count");
  d.field_names.resize(fields);
  for (std::string& name : d.field_names) {
    if (!r.Text(name)) return bad("field names");
  }
  uint8_t normalize = 0, linear = 0;
  if (!r.Scalar(d.min_weight) || !r.Scalar(normalize) || !r.Scalar(linear)) return bad("flags");
  d.normalize = normalize != 0;
  d.linear_terms = linear != 0;
  std::array<double, 10> st{};
  for (double& v : st) {
    if (!r.Scalar(v)) return bad("statistics");
  }
  VolumeFieldStats& s = d.stats;
  s.epsilon = st[0];
  s.iterations = static_cast<int>(st[1]);
  s.chosen_by_cross_validation = st[2] != 0;
  s.cross_validation_rms = st[3];
  s.cross_validation_points = static_cast<int>(st[4]);
  s.spectral_radius = st[5];
  s.kernels_per_vertex = st[6];
  s.median_spacing = st[7];
  s.mean_star_size = st[8];
  s.seconds = st[9];
  float cutoff2 = 0;
  std::vector<KernelRecord> records;
  if (!r.Scalar(cutoff2) || !r.Array(records) || records.empty()) return bad("kernels");
  const uint64_t n = records.size();
  if (!r.Array(impl->positions, n) || !r.Array(impl->spacing, n)) return bad("vertices");
  impl->values.resize(fields);
  impl->gradients.resize(fields);
  impl->g.resize(fields);
  impl->big_g.resize(fields);
  for (size_t f = 0; f < fields; ++f) {
    if (!r.Array(impl->values[f], n) || !r.Array(impl->gradients[f], n) || !r.Array(impl->g[f], n) ||
        !r.Array(impl->big_g[f], n)) {
      return bad("coefficients");
    }
  }
  std::vector<Vec3f> cell_positions;
  std::vector<std::array<uint32_t, 4>> tets;
  if (!r.Array(cell_positions) || !r.Array(tets) || !r.AtEnd()) return bad("cells");
  for (const auto& t : tets) {
    for (uint32_t v : t) {
      if (v >= cell_positions.size()) return bad("a tetrahedron refers to a missing vertex");
    }
  }
  for (const Vec3f& p : impl->positions) d.bounds.extend(p.cast<double>());
  std::unique_ptr<CellLocator> locator;
  if (!tets.empty()) locator = std::make_unique<CellLocator>(std::move(cell_positions), std::move(tets));
  impl->kernels = std::make_unique<Kernels>(std::move(records), cutoff2);
  impl->Pack(d.linear_terms);
  return std::make_unique<VolumeField>(std::move(d), std::move(impl), std::move(locator));
}

}  // namespace lsqsurf::volume
