// worker/volume/volume_field.h — anisotropic iaMLS reconstruction of scalar fields given on the
// vertices of a volume mesh or a point set (seed §5; METHODS.md §4).
//
// Every vertex i carries a Laguerre–Gaussian generating function of order 1, measured in its own
// metric and scaled to the volume V_i it stands for:
//     Ψ_i(x) = V_i ε³/(π^{3/2} H_i³) · (5/2 − s) e^{−s},   s = ε² (x − x_i)ᵀ M_i (x − x_i) / H_i²,
// M_i the star's unit-determinant metric (stars.h) and H_i = spacing_scale · V_i^{1/3} (or the
// given spacing h). Each Ψ_i integrates to V_i and has no second moment, so Σ_i f_i Ψ_i
// reproduces quadratics up to a small saturation error wherever the vertices fill space.
//
// Precomputation (seed eqs. 16–20): g⁽⁰⁾ = f, g⁽ʲ⁺¹⁾ = g⁽ʲ⁾ + (f − A g⁽ʲ⁾), A_ki = Ψ_i(x_k)
// (Richardson iteration towards the interpolant), and the same for the least-squares gradients
// ∇f_i, giving G. Then Q_f(x) = Σ g_i Ψ_i(x) and Q_∇f(x) = Σ G_i Ψ_i(x): the gradient field is
// the iaMLS reconstruction of the gradients, not the derivative of Q_f. The iteration converges
// when the spectral radius of I − A is below 1; it is estimated by power steps and a setting
// that diverges is refused with a message saying what to change.
//
// Normalisation: on irregular vertices the plain sum Σ Ψ_i(x) is far from 1 (measured: ±20 % at
// ε = 1 on a lattice jittered by 0.3 spacing, where the iteration then needs many steps to undo
// it), so by default both the iteration's matrix and the evaluation divide by it:
// Q_f(x) = Σ g_i Ψ_i(x) / Σ Ψ_i(x), constants are reproduced exactly, and the seed's plain sum
// stays available (`normalize` off).
//
// Linear terms: by default each kernel carries its vertex's value plus the linear term of its
// least-squares gradient, Q_f(x) = Σ (g_i + ∇f_i·(x − x_i)) Ψ_i(x) / Σ Ψ_i(x), as the seed's
// iaMLS surfaces carry tangent planes; the iteration then treats Σ_i A_ki ∇f_i·(x_k − x_i) as a
// fixed term. Linear fields come back exactly on any vertices, and the error falls at second
// order or better where values alone stall at first order (measured: Franke on a jittered
// 25³ lattice, 1.5e-4 RMS against 6.3e-4 without). `linear_terms` off gives the seed's form.
//
// Automatic parameters (the seed's future work): unless given, ε and the iteration count are
// chosen per dataset by leave-out cross-validation: up to four neighbourhoods of about 10,000
// vertices, 4 % of their inner vertices held out (their volume shared among their neighbours),
// every candidate ε and iteration count scored by the RMS error at the held-out vertices; among
// the scores within 2 % of the best the largest ε wins (the narrowest kernel, the fastest
// evaluation).
//
// Evaluation sums over the kernels whose supports (ε √s ≤ cutoff, an ellipsoid per vertex)
// hold x, found in a uniform grid of the supports' bounding boxes. Thread-safe after building.
#pragma once

#include <array>
#include <limits>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"
#include "worker/volume/cell_locator.h"
#include "worker/volume/stars.h"
#include "worker/volume/volume_mesh.h"

namespace lsqsurf::volume {

struct VolumeFieldParams {
  double epsilon = 0;          // Kernel shape ε, 0.3..2.5; 0 = chosen by cross-validation.
  int iterations = -1;         // Richardson steps, 0..20; −1 = chosen by cross-validation.
  double spacing = 0;          // H in model units for every vertex; 0 = spacing_scale × V_i^{1/3}.
  double spacing_scale = 1;    // 0.5..4, used when `spacing` is 0.
  bool anisotropic = true;     // Kernels in the star metrics; false = round kernels.
  double max_anisotropy = 20;  // Largest ratio of a kernel's axes, 1..1000.
  bool normalize = true;       // Q = Σ g_i Ψ_i / Σ Ψ_i (see above); false = the seed's plain sum.
  bool linear_terms = true;    // Kernels carry g_i + ∇f_i·(x − x_i) (see above); false = g_i alone.
  double cutoff = 3;           // Kernels end at ε √s = cutoff, 2..6 (at 3 the tail holds ~0.3 % of the mass).
  GradientWeights gradient_weights = GradientWeights::kGaussian;
  int neighbors = 16;       // k of the nearest-neighbour stars of a point set, 6..64.
  double min_weight = 0.5;  // Point sets: the domain is where ΣΨ ≥ min_weight, 0.05..1.
};

const core::ParamTable<VolumeFieldParams>& VolumeFieldParamTable();
absl::Status Validate(const VolumeFieldParams& params);

struct VolumeFieldStats {
  double epsilon = 0;
  int iterations = 0;
  bool chosen_by_cross_validation = false;
  double cross_validation_rms = 0;  // Held-out RMS error of the choice (field units); 0 if none ran.
  int cross_validation_points = 0;
  double spectral_radius = 0;     // Of I − A (estimated); the iteration needs it below 1.
  double kernels_per_vertex = 0;  // Mean non-zeros per row of A.
  double median_spacing = 0;      // Median mean star edge, model units.
  double mean_star_size = 0;
  int64_t widened_stars = 0;
  int64_t singular_stars = 0;
  std::vector<double> residuals;  // max_i |f_i − Q_f(x_i)| before each iteration and after the last (first field).
  double seconds = 0;
};

struct KernelSum;

class VolumeField {
 public:
  struct Sample {
    double value = std::numeric_limits<double>::quiet_NaN();  // Q_f; NaN where no kernel reaches.
    Vec3d gradient = Vec3d::Zero();                           // Q_∇f.
    double weight = 0;                                        // ΣΨ_i(x).
  };

  Sample Evaluate(const Vec3d& x, int field) const;
  // Inside the input's cells, or (point sets) where ΣΨ ≥ min_weight. `weight` is Sample::weight.
  bool InDomain(const Vec3d& x, double weight) const;
  // Evaluate at many points, in parallel. Errors: kCancelled.
  absl::Status EvaluateBatch(std::span<const Vec3d> xs, int field, std::span<Sample> out,
                             const core::JobContext* ctx = nullptr) const;

  const std::vector<std::string>& field_names() const { return description_.field_names; }
  int FieldIndex(std::string_view name) const;  // −1 when absent.
  const VolumeFieldStats& stats() const { return description_.stats; }
  const core::Box3& bounds() const { return description_.bounds; }
  // The input vertices and, per field, their data values and least-squares gradients.
  std::span<const Vec3f> positions() const;
  std::span<const float> data_values(int field) const;
  std::span<const Vec3f> data_gradients(int field) const;
  std::span<const float> data_spacing() const;  // Mean star edge per vertex.
  const CellLocator* locator() const { return locator_.get(); }

  // What a field is besides its kernels and cells.
  struct Description {
    std::vector<std::string> field_names;
    VolumeFieldStats stats;
    core::Box3 bounds;
    double min_weight = 0.5;
    bool normalize = true;
    bool linear_terms = true;
  };
  // The kernels and coefficients, defined in volume_field.cc: only BuildVolumeField and
  // DeserializeVolumeField make them, so the constructor and accessor open nothing to other modules.
  struct Impl;
  VolumeField(Description description, std::shared_ptr<const Impl> impl, std::unique_ptr<CellLocator> locator);
  const Description& description() const { return description_; }
  const Impl& impl() const { return *impl_; }

 private:
  Sample ToSample(const KernelSum& sum) const;
  Description description_;
  std::shared_ptr<const Impl> impl_;
  std::unique_ptr<CellLocator> locator_;
};

// Reconstructs the named scalar fields (all of them share the kernels; the first drives the
// cross-validation). The mesh must be valid (ValidateVolumeMesh).
// Errors: kInvalidArgument (a name that is not a scalar field of the mesh — the message lists
// those present —, bad parameters, a diverging ε/iteration setting), kCancelled.
absl::StatusOr<std::unique_ptr<VolumeField>> BuildVolumeField(const VolumeMesh& mesh,
                                                              std::span<const std::string> field_names,
                                                              const VolumeFieldParams& params, core::JobContext& ctx);

// The precomputed field in a binary form that a later job reads back without recomputing it:
// kernels, coefficients, data values and gradients, the domain's tetrahedra and the statistics
// (native little-endian floats; about 90 bytes per vertex and field plus 28 per tetrahedron).
std::string SerializeVolumeField(const VolumeField& field);
// Whether `bytes` begin like a stored field (no further check).
bool IsStoredVolumeField(std::string_view bytes);
// Errors: kInvalidArgument (not a stored field, truncated or inconsistent).
absl::StatusOr<std::unique_ptr<VolumeField>> DeserializeVolumeField(std::string_view bytes);

}  // namespace lsqsurf::volume
