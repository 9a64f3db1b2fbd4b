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
#include <functional>
#include <optional>
#include <span>

#include "worker/core/geometry.h"
#include "worker/pu/orthogonal_fit.h"

namespace lsqsurf::pu {

using core::Vec3d;

// A sheet's height p(u, v) of degree ≤ 2 in monomials 1, u, v, u², uv, v² (BivariatePolynomial's
// order): the six coefficients that degree uses, not the fifteen of degree 4, so that a fit of
// kMaxSheets sheets stays as small as four general ones.
struct SheetHeight {
  std::array<double, 6> coefficients{};
  int32_t degree = 0;

  void Evaluate(double u, double v, double& value, double& du, double& dv) const;
};

// One smooth piece: normal·(x − origin) − p(u, v), (u, v) the tangent coordinates / scale.
struct Sheet {
  Vec3d origin = Vec3d::Zero();
  Vec3d tangent_u = Vec3d::UnitX(), tangent_v = Vec3d::UnitY(), normal = Vec3d::UnitZ();
  double scale = 1;
  SheetHeight height;

  double Evaluate(const Vec3d& x, Vec3d* gradient) const;
};

enum class Feature : int8_t { kSmooth = 0, kEdge = 1, kCorner = 2 };

// Sheets of one fit: a corner of up to six faces (a seventh face's points join the nearest sheet,
// and such a fit misses the bound; the cells split instead).
inline constexpr int kMaxSheets = 6;

struct SharpFit {
  std::array<Sheet, kMaxSheets> sheets;
  int count = 0;
  // The left fold f = op_{k−1}(… op_0(f_0, f_1) …, f_k); op_k is max where take_max[k].
  std::array<bool, kMaxSheets - 1> take_max{};
  Feature feature = Feature::kEdge;

  // F and ∇F of the piece that the max/min selects.
  double Evaluate(const Vec3d& x, Vec3d* gradient) const;
};

struct SharpParams {
  double edge_cos = 0.9;      // Two normals closer than this (cosine) show no edge (MPU's edgeT).
  double corner_share = 0.7;  // |(n_a × n_b)·n_i| above this for some point makes a corner (cornerT).
  // FitSharpClusters' second try, where the first misses the bound: faces whose normals differ by
  // less than edge_cos (a polytope's shallow edge beside a sharp corner) get sheets of their own.
  double fine_cos = 0.98;
  // Its third try: faces 6-11 degrees apart at a corner of many (a random convex hull's corners of
  // seven and nine faces, a few pairs 7-8 degrees apart, were cut 1.1e-3 of the diagonal deep).
  // Tight clusters within half the seeding angle, not a quarter, were tried instead: they gave the
  // smooth bunny 1403 corner fits instead of 18.
  double finest_cos = 0.995;
};

// A sharp fit to weighted oriented points (weights ≥ 0), or nothing when their normals show no
// crease or the clusters cannot be combined consistently. `scale` is the fitting radius.
std::optional<SharpFit> FitSharp(std::span<const Vec3d> points, std::span<const Vec3d> normals,
                                 std::span<const double> weights, double scale, const SharpParams& params,
                                 OrthogonalFitter& fitter);

// The same for corners of more faces (a polytope's corner where five or more meet, or four that
// the test above splits wrongly): the normals are clustered by farthest-point seeding, every
// normal more than edge_cos from the seeds so far seeding a new sheet (at most kMaxSheets), and
// the clusters must be tight (each within a quarter of the seeding angle of its mean normal) and
// apart (no two normals of different ones within half of it: a smooth patch is not cut into
// sheets), and
// the sheets combine only where every pair is alike (all max or all min). Tried where FitSharp's
// fit misses the error bound. One clustering per entry of `seed_cos` (edge_cos, fine_cos, finest_cos),
// each fit handed to `take`, until it returns true.
void FitSharpClusters(std::span<const Vec3d> points, std::span<const Vec3d> normals, std::span<const double> weights,
                      double scale, std::span<const double> seed_cos, const std::function<bool(const SharpFit&)>& take,
                      OrthogonalFitter& fitter);

}  // namespace lsqsurf::pu
