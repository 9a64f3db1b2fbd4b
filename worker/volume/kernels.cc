// The vector helpers here (and TwoToThe from the header, instantiated on vectors only here) are
// internal to this file, so the warning that their calling convention differs between the AVX
// clone and the rest does not apply.
#pragma GCC diagnostic ignored "-Wpsabi"

#include "worker/volume/kernels.h"

#include <tbb/parallel_sort.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cstring>
#include <numbers>

#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::volume {
namespace {

Eigen::Matrix3d ShapeMatrix(const std::array<float, 6>& q) {
  Eigen::Matrix3d s;
  s << q[0], q[3] / 2, q[4] / 2, q[3] / 2, q[1], q[5] / 2, q[4] / 2, q[5] / 2, q[2];
  return s;
}

// Points are summed in groups of at most this many that share a grid bin.
constexpr size_t kGroupSize = 64;

// Eight floats, one per kernel, in the compiler's vector extension: two SSE registers on any
// x86-64, one AVX register in the clone built for CPUs that have it.
using Lanes = float __attribute__((vector_size(32)));
using IntLanes = int32_t __attribute__((vector_size(32)));
constexpr size_t kLanes = 8;

// The rows of a group's kernels, each `stride` floats long (a multiple of kLanes; the padding
// kernels have zero weight).
enum Row { kCx, kCy, kCz, kQ0, kQ1, kQ2, kQ3, kQ4, kQ5, kWeight, kG, kSx, kSy, kSz, kGx, kGy, kGz, kRows };

// The helpers on Lanes are always inlined: the vector clones of SumGroup below are compiled for
// AVX, which passes a 32-byte vector in one register, while an out-of-line helper compiled for
// the baseline takes it in memory; a call between the two reads garbage (seen at -O1, where
// GCC did not inline them).
[[gnu::always_inline]] inline Lanes Load(const float* p) {
  Lanes v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

// ExpOfMinus on eight values at once (s ≥ 0).
[[gnu::always_inline]] inline Lanes ExpOfMinusLanes(Lanes s) {
  const Lanes t = s * 1.44269504f;
  const IntLanes k = __builtin_convertvector(t + 0.5f, IntLanes);  // Truncation is floor here.
  const IntLanes bits = (127 - k) << 23;
  return TwoToThe(__builtin_convertvector(k, Lanes) - t) * std::bit_cast<Lanes>(bits);
}

// Not under ThreadSanitizer: the clones' resolver runs while the program loads, before the
// sanitizer's runtime is ready, and crashes there.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(__SANITIZE_THREAD__)
#define LSQSURF_VECTOR_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define LSQSURF_VECTOR_CLONES
#endif

// Sums over `rows` (kRows rows of `stride`) at `points` (relative to the same origin as the rows'
// centres).
LSQSURF_VECTOR_CLONES
void SumGroup(const float* rows, size_t stride, float cutoff2, std::span<const Vec3f> points, KernelSum* out) {
  const float* row[kRows];
  for (int r = 0; r < kRows; ++r) row[r] = rows + r * stride;
  for (size_t k = 0; k < points.size(); ++k) {
    const Vec3f& x = points[k];
    Lanes w{}, v{}, gx{}, gy{}, gz{};
    for (size_t j = 0; j < stride; j += kLanes) {
      const Lanes dx = x[0] - Load(row[kCx] + j), dy = x[1] - Load(row[kCy] + j), dz = x[2] - Load(row[kCz] + j);
      const Lanes s = Load(row[kQ0] + j) * dx * dx + Load(row[kQ1] + j) * dy * dy + Load(row[kQ2] + j) * dz * dz +
                      Load(row[kQ3] + j) * dx * dy + Load(row[kQ4] + j) * dx * dz + Load(row[kQ5] + j) * dy * dz;
      const auto inside = s < cutoff2;
      const Lanes e = ExpOfMinusLanes(inside ? s : cutoff2);
      const Lanes psi = inside ? Load(row[kWeight] + j) * (2.5f - s) * e : Lanes{};
      w += psi;
      v += psi * (Load(row[kG] + j) + Load(row[kSx] + j) * dx + Load(row[kSy] + j) * dy + Load(row[kSz] + j) * dz);
      gx += psi * Load(row[kGx] + j);
      gy += psi * Load(row[kGy] + j);
      gz += psi * Load(row[kGz] + j);
    }
    KernelSum& o = out[k];
    for (size_t l = 0; l < kLanes; ++l) {
      o.weight += w[l];
      o.value += v[l];
      o.gradient += Vec3d(gx[l], gy[l], gz[l]);
    }
  }
}

// 8 bits per axis interleaved: the order of points inside one bin.
uint64_t Morton24(const Vec3d& within) {
  uint64_t code = 0;
  for (int bit = 7; bit >= 0; --bit) {
    for (int a = 2; a >= 0; --a) code = code << 1 | ((static_cast<uint64_t>(within[a] * 256) >> bit) & 1);
  }
  return code;
}

}  // namespace

Kernels::Kernels(std::span<const Vec3f> centers, std::span<const Sym3> metric, std::span<const float> volume,
                 const VolumeFieldParams& p, double eps) {
  const size_t n = centers.size();
  records_.resize(n);
  cutoff2_ = static_cast<float>(p.cutoff * p.cutoff);
  const double eps3 = eps * eps * eps / std::pow(std::numbers::pi, 1.5);
  for (size_t i = 0; i < n; ++i) {
    const double v = std::max<double>(volume[i], 1e-30);
    const double h = p.spacing > 0 ? p.spacing : p.spacing_scale * std::cbrt(v);
    Eigen::Matrix3d m = Eigen::Matrix3d::Identity();
    if (p.anisotropic) {
      const Sym3& s = metric[i];
      m << s[0], s[3], s[4], s[3], s[1], s[5], s[4], s[5], s[2];
    }
    const Eigen::Matrix3d s = (eps * eps / (h * h)) * m;
    KernelRecord& r = records_[i];
    r.center = centers[i];
    r.weight = static_cast<float>(eps3 * v / (h * h * h));
    r.shape = {static_cast<float>(s(0, 0)),     static_cast<float>(s(1, 1)),     static_cast<float>(s(2, 2)),
               static_cast<float>(2 * s(0, 1)), static_cast<float>(2 * s(0, 2)), static_cast<float>(2 * s(1, 2))};
  }
  BuildGrid();
}

Kernels::Kernels(std::vector<KernelRecord> records, float cutoff2) : records_(std::move(records)), cutoff2_(cutoff2) {
  BuildGrid();
}

void Kernels::BuildGrid() {
  const size_t n = records_.size();
  // The ellipsoid dᵀ S d ≤ c² reaches c √((S⁻¹)_aa) along axis a.
  std::vector<Vec3f> extent(n);
  reach_scale_.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Matrix3d s = ShapeMatrix(records_[i].shape);
    const Eigen::Matrix3d inv = s.inverse();
    for (int a = 0; a < 3; ++a) extent[i][a] = std::sqrt(static_cast<float>(cutoff2_ * inv(a, a)));
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen;
    eigen.computeDirect(s, Eigen::EigenvaluesOnly);
    // A little slack: the bound only decides which kernels a group of points tests.
    reach_scale_[i] = static_cast<float>(1.001 * std::sqrt(std::max(eigen.eigenvalues()[2], 0.0)));
  }
  auto support = [&](size_t i) {
    return core::Box3((records_[i].center - extent[i]).cast<double>(), (records_[i].center + extent[i]).cast<double>());
  };
  core::Box3 bounds;
  for (size_t i = 0; i < n; ++i) bounds.extend(support(i));
  // Bins of two thirds of the median reach: a support spans about 4 bins per axis and a query
  // tests ~4.5 kernels for each one that reaches it. At most ~16M bins.
  Vec3d bin_size;
  std::vector<float> e(n);
  for (int a = 0; a < 3; ++a) {
    for (size_t i = 0; i < n; ++i) e[i] = extent[i][a];
    std::nth_element(e.begin(), e.begin() + static_cast<int64_t>(n / 2), e.end());
    bin_size[a] = std::max(2.0 / 3.0 * e[n / 2], bounds.sizes()[a] / 2048.0);
  }
  grid_ = BoxGrid(bounds, bin_size, 16e6, n, support);
}

KernelSum Kernels::Sum(const Vec3d& x, std::span<const KernelCoefficients> coefficients) const {
  KernelSum out;
  ForEach(x, [&](uint32_t i, float psi, const Vec3f& d) {
    const KernelCoefficients& c = coefficients[i];
    out.weight += psi;
    out.value += psi * (c.g + c.slope.dot(d));
    out.gradient += (psi * c.big_g).cast<double>();
  });
  return out;
}

absl::Status Kernels::SumBatch(std::span<const Vec3d> xs, std::span<const KernelCoefficients> coefficients,
                               std::span<KernelSum> out, const core::JobContext* ctx) const {
  const size_t n = xs.size();
  // Points by bin, and along a Morton curve inside each bin; those outside the grid last.
  std::vector<std::pair<uint64_t, uint32_t>> keyed(n);
  std::vector<int64_t> bin(n);
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        for (size_t k = begin; k < end; ++k) {
          Vec3d within;
          bin[k] = grid_.Locate(xs[k], &within);
          const uint64_t key = bin[k] < 0 ? UINT64_MAX : static_cast<uint64_t>(bin[k]) << 24 | Morton24(within);
          keyed[k] = {key, static_cast<uint32_t>(k)};
        }
      },
      ctx));
  tbb::parallel_sort(keyed.begin(), keyed.end());
  std::vector<size_t> group_start;
  size_t inside = 0;
  for (; inside < n && keyed[inside].first != UINT64_MAX; ++inside) {
    if (inside == 0 || keyed[inside].first >> 24 != keyed[inside - 1].first >> 24 ||
        inside - group_start.back() == kGroupSize) {
      group_start.push_back(inside);
    }
  }
  for (size_t k = inside; k < n; ++k) out[keyed[k].second] = KernelSum{};
  group_start.push_back(inside);
  const float cutoff = std::sqrt(cutoff2_);
  return core::ParallelFor(
      group_start.size() - 1, 8,
      [&](size_t first_group, size_t last_group) {
        std::vector<float> rows;
        std::vector<uint32_t> reach;
        std::vector<Vec3f> points;
        std::vector<KernelSum> sums;
        for (size_t group = first_group; group < last_group; ++group) {
          const size_t begin = group_start[group], end = group_start[group + 1];
          core::Box3 box;
          for (size_t k = begin; k < end; ++k) box.extend(xs[keyed[k].second]);
          const Vec3d origin = box.center();
          const float radius = static_cast<float>(0.5 * box.diagonal().norm());
          // The kernels whose support can meet the group's box: |x − c|_S ≥ |o − c|_S − σ_max r.
          reach.clear();
          for (const uint32_t i : grid_.Items(bin[keyed[begin].second])) {
            const KernelRecord& r = records_[i];
            const float s = r.Form((origin - r.center.cast<double>()).cast<float>());
            if (std::sqrt(s) < cutoff + reach_scale_[i] * radius) reach.push_back(i);
          }
          const size_t stride = (reach.size() + kLanes - 1) / kLanes * kLanes;
          rows.assign(kRows * stride, 0.0f);
          for (size_t j = 0; j < reach.size(); ++j) {
            const KernelRecord& r = records_[reach[j]];
            const KernelCoefficients& c = coefficients[reach[j]];
            const Vec3f centre = (r.center.cast<double>() - origin).cast<float>();
            const float values[kRows] = {centre[0],  centre[1],  centre[2],  r.shape[0], r.shape[1], r.shape[2],
                                         r.shape[3], r.shape[4], r.shape[5], r.weight,   c.g,        c.slope[0],
                                         c.slope[1], c.slope[2], c.big_g[0], c.big_g[1], c.big_g[2]};
            for (int row = 0; row < kRows; ++row) rows[row * stride + j] = values[row];
          }
          points.resize(end - begin);
          for (size_t k = begin; k < end; ++k) points[k - begin] = (xs[keyed[k].second] - origin).cast<float>();
          sums.assign(end - begin, KernelSum{});
          SumGroup(rows.data(), stride, cutoff2_, points, sums.data());
          for (size_t k = begin; k < end; ++k) out[keyed[k].second] = sums[k - begin];
        }
      },
      ctx);
}

}  // namespace lsqsurf::volume
