// worker/pu/sharp_fit.h — local fits with sharp edges and corners (METHODS §1.7, after Ohtake et
// al.'s multi-level partition of unity).
//
// Where the normals of a cell's points split into two clusters (an edge) or three or four (a
// corner), each cluster gets its own sheet: a height polynomial of degree ≤ 2 over its own
// tangent plane, in orthogonal polynomials (orthogonal_fit.h). The sheets are combined with max
// where the solid is convex between them and min where it is concave, so the local function
// keeps the crease instead of rounding it. F > 0 on the side the normals point to.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>

#include "worker/core/geometry.h"
#include "worker/pu/orthogonal_fit.h"

namespace lsqsurf::pu {

using core::Vec3d;

// One smooth piece: normal·(x − origin) − p(u, v), (u, v) the tangent coordinates / scale.
struct Sheet {
  Vec3d origin = Vec3d::Zero();
  Vec3d tangent_u = Vec3d::UnitX(), tangent_v = Vec3d::UnitY(), normal = Vec3d::UnitZ();
  double scale = 1;
  BivariatePolynomial height;  // Degree 0–2.

  double Evaluate(const Vec3d& x, Vec3d* gradient) const;
};

enum class Feature : int8_t { kSmooth = 0, kEdge = 1, kCorner = 2 };

struct SharpFit {
  std::array<Sheet, 4> sheets;
  int count = 0;
  // The left fold f = op_{k−1}(… op_0(f_0, f_1) …, f_k); op_k is max where take_max[k].
  std::array<bool, 3> take_max{};
  Feature feature = Feature::kEdge;

  // F and ∇F of the piece that the max/min selects.
  double Evaluate(const Vec3d& x, Vec3d* gradient) const;
};

struct SharpParams {
  double edge_cos = 0.9;      // Two normals closer than this (cosine) show no edge (MPU's edgeT).
  double corner_share = 0.7;  // |(n_a × n_b)·n_i| above this for some point makes a corner (cornerT).
};

// A sharp fit to weighted oriented points (weights ≥ 0), or nothing when their normals show no
// crease or the clusters cannot be combined consistently. `scale` is the fitting radius.
std::optional<SharpFit> FitSharp(std::span<const Vec3d> points, std::span<const Vec3d> normals,
                                 std::span<const double> weights, double scale, const SharpParams& params,
                                 OrthogonalFitter& fitter);

}  // namespace lsqsurf::pu
