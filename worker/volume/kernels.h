// worker/volume/kernels.h — the generating functions of a volume field (anisotropic
// Laguerre–Gaussians, one per vertex) and sums over them: one point at a time for the
// precomputation and the isosurface, and a vectorised batch for probes and rendering grids.
#pragma once

#include <absl/status/status.h>

#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <span>
#include <vector>

#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/volume/box_grid.h"
#include "worker/volume/volume_field.h"

namespace lsqsurf::volume {

using core::Vec3d;
using core::Vec3f;

// 2^r for r ∈ [−½, ½] by its Taylor polynomial of degree 6: for a float, or for the batch
// path's vector of floats.
template <class T>
[[gnu::always_inline]] inline T TwoToThe(T r) {
  T p = r * 1.5403530e-4f + 1.3333558e-3f;
  p = p * r + 9.6181291e-3f;
  p = p * r + 5.5504109e-2f;
  p = p * r + 2.4022651e-1f;
  p = p * r + 6.9314718e-1f;
  return p * r + 1.0f;
}

// e^{-s} for 0 ≤ s ≤ 12 (beyond the cutoff) to a relative 1e-6, inline: evaluations spend most
// of their time here, and the library call neither inlines nor vectorises.
// e^{-s} = 2^{-t}, t = s log₂e = k − r with k the nearest integer: exponent bits times 2^r.
inline float ExpOfMinus(float s) {
  const float t = s * 1.44269504f;
  const float k = std::floor(t + 0.5f);
  return TwoToThe(k - t) * std::bit_cast<float>((127 - static_cast<int32_t>(k)) << 23);
}

// One generating function: Ψ(x) = weight (5/2 − s) e^{−s}, s = dᵀ S d, d = x − center, for
// s below the cutoff. S = ε² M / H², weight ε³ V / (π^{3/2} H³). Stored as is in a kept field.
struct KernelRecord {
  Vec3f center;
  float weight;
  std::array<float, 6> shape;  // S: xx, yy, zz, 2xy, 2xz, 2yz

  float Form(const Vec3f& d) const {  // dᵀ S d.
    const auto& q = shape;
    return q[0] * d[0] * d[0] + q[1] * d[1] * d[1] + q[2] * d[2] * d[2] + q[3] * d[0] * d[1] + q[4] * d[0] * d[2] +
           q[5] * d[1] * d[2];
  }
};

// What a sum reads of each kernel besides its shape: the value term g + slope·(x − center)
// and the gradient term G (VolumeField's g_i, ∇f_i or 0, G_i).
struct KernelCoefficients {
  float g;
  Vec3f slope;
  Vec3f big_g;
  float unused;
};

// Σ Ψ_i, Σ Ψ_i (g_i + slope_i·d_i), Σ Ψ_i G_i at a point.
struct KernelSum {
  double weight = 0;
  double value = 0;
  Vec3d gradient = Vec3d::Zero();
};

class Kernels {
 public:
  // The kernels of a vertex set for one ε (centres, star metrics and volumes per vertex).
  Kernels(std::span<const Vec3f> centers, std::span<const Sym3> metric, std::span<const float> volume,
          const VolumeFieldParams& p, double eps);
  // Kernels read back from a stored field.
  Kernels(std::vector<KernelRecord> records, float cutoff2);

  size_t size() const { return records_.size(); }
  const std::vector<KernelRecord>& records() const { return records_; }
  float cutoff2() const { return cutoff2_; }

  // Calls f(i, Ψ_i(x), x − x_i) for every kernel whose support holds x.
  template <class F>
  void ForEach(const Vec3d& x, F&& f) const {
    const Vec3f xf = x.cast<float>();
    for (const uint32_t i : grid_.At(x)) {
      const KernelRecord& r = records_[i];
      const Vec3f d = xf - r.center;
      const float s = r.Form(d);
      if (s >= cutoff2_) continue;
      f(i, r.weight * (2.5f - s) * ExpOfMinus(s), d);
    }
  }

  KernelSum Sum(const Vec3d& x, std::span<const KernelCoefficients> coefficients) const;

  // Sum at each of xs, in parallel: the points are taken in groups of nearby ones, each group
  // against the kernels that can reach it, eight kernels at a time. Errors: kCancelled.
  absl::Status SumBatch(std::span<const Vec3d> xs, std::span<const KernelCoefficients> coefficients,
                        std::span<KernelSum> out, const core::JobContext* ctx) const;

 private:
  void BuildGrid();

  std::vector<KernelRecord> records_;
  // √ of S's largest eigenvalue: |d|_S ≤ reach_scale |d|, to bound s over a box of points.
  std::vector<float> reach_scale_;
  float cutoff2_ = 9;
  BoxGrid grid_;
};

}  // namespace lsqsurf::volume
