#include "worker/pu/sharp_fit.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <numbers>
#include <vector>

namespace lsqsurf::pu {
namespace {

// A sheet needs twice its terms in points: a quadric height from 12, a tilted plane from 6;
// fewer make the plane through the cluster's centroid with its mean normal.
constexpr int kQuadraticPoints = 12;
constexpr int kPlanePoints = 6;

// One cluster's sheet over its own weighted tangent plane.
Sheet FitSheet(std::span<const Vec3d> points, std::span<const Vec3d> normals, std::span<const double> weights,
               std::span<const uint32_t> members, double scale, OrthogonalFitter& fitter) {
  Sheet s;
  Vec3d centroid = Vec3d::Zero(), normal = Vec3d::Zero();
  double total = 0;
  int weighted = 0;
  for (uint32_t i : members) {
    centroid += weights[i] * points[i];
    normal += weights[i] * normals[i];
    total += weights[i];
    weighted += weights[i] > 0;
  }
  s.origin = centroid / total;
  s.normal = normal.normalized();
  s.tangent_u = s.normal.unitOrthogonal();
  s.tangent_v = s.normal.cross(s.tangent_u);
  s.scale = scale;
  if (weighted < kPlanePoints) return s;
  std::vector<double> u, v, w, wt;
  for (uint32_t i : members) {
    const Vec3d d = points[i] - s.origin;
    u.push_back(s.tangent_u.dot(d) / scale);
    v.push_back(s.tangent_v.dot(d) / scale);
    w.push_back(s.normal.dot(d));
    wt.push_back(weights[i]);
  }
  fitter.Reset(u, v, w, wt);
  if (fitter.RaiseDegree() && weighted >= kQuadraticPoints) fitter.RaiseDegree();
  const BivariatePolynomial& p = fitter.polynomial();
  s.height.degree = std::min(p.degree, 2);
  std::copy_n(p.coefficients.begin(), TermCount(s.height.degree), s.height.coefficients.begin());
  return s;
}

// MPU's test: the solid is convex between sheets a and b when the angle from a's centroid offset
// to a's normal plus the one from the opposite offset to b's normal stays below π.
bool Convex(const Sheet& a, const Sheet& b) {
  const Vec3d v = a.origin - b.origin;
  if (!(v.norm() > 0)) return true;
  auto angle = [](const Vec3d& p, const Vec3d& q) {
    return std::acos(std::clamp(p.normalized().dot(q.normalized()), -1.0, 1.0));
  };
  return angle(v, a.normal) + angle(-v, b.normal) < std::numbers::pi;
}

// The closest pair of directions among the normals: indices with the smallest dot product.
std::pair<uint32_t, uint32_t> WidestPair(std::span<const Vec3d> normals, std::span<const uint32_t> members,
                                         double& smallest) {
  smallest = 2;
  std::pair<uint32_t, uint32_t> best{members[0], members[0]};
  for (size_t i = 0; i < members.size(); ++i) {
    for (size_t j = i + 1; j < members.size(); ++j) {
      const double d = normals[members[i]].dot(normals[members[j]]);
      if (d < smallest) smallest = d, best = {members[i], members[j]};
    }
  }
  return best;
}

// The points that carry weight.
std::vector<uint32_t> WeightedMembers(std::span<const double> weights) {
  std::vector<uint32_t> members;
  for (uint32_t i = 0; i < weights.size(); ++i) {
    if (weights[i] > 0) members.push_back(i);
  }
  return members;
}

// One sheet per group into `fit` (its count given); false where a group is empty.
bool FitSheets(std::span<const Vec3d> points, std::span<const Vec3d> normals, std::span<const double> weights,
               std::span<const std::vector<uint32_t>> groups, double scale, OrthogonalFitter& fitter, SharpFit& fit) {
  for (int k = 0; k < fit.count; ++k) {
    if (groups[static_cast<size_t>(k)].empty()) return false;
    fit.sheets[static_cast<size_t>(k)] =
        FitSheet(points, normals, weights, groups[static_cast<size_t>(k)], scale, fitter);
  }
  return true;
}

// Whether every pair of the fit's sheets is convex between them, or every pair concave; which
// one in `all_convex`.
bool AllPairsAlike(const SharpFit& fit, bool& all_convex) {
  all_convex = true;
  bool all_concave = true;
  for (int i = 0; i < fit.count; ++i) {
    for (int j = i + 1; j < fit.count; ++j) {
      const bool c = Convex(fit.sheets[static_cast<size_t>(i)], fit.sheets[static_cast<size_t>(j)]);
      all_convex &= c;
      all_concave &= !c;
    }
  }
  return all_convex || all_concave;
}

}  // namespace

void SheetHeight::Evaluate(double u, double v, double& value, double& du, double& dv) const {
  const auto& c = coefficients;  // Zero beyond the degree.
  value = c[0] + c[1] * u + c[2] * v + c[3] * u * u + c[4] * u * v + c[5] * v * v;
  du = c[1] + 2 * c[3] * u + c[4] * v;
  dv = c[2] + c[4] * u + 2 * c[5] * v;
}

double Sheet::Evaluate(const Vec3d& x, Vec3d* gradient) const {
  const Vec3d d = x - origin;
  double h, hu, hv;
  height.Evaluate(tangent_u.dot(d) / scale, tangent_v.dot(d) / scale, h, hu, hv);
  if (gradient) *gradient = normal - (hu * tangent_u + hv * tangent_v) / scale;
  return normal.dot(d) - h;
}

double SharpFit::Evaluate(const Vec3d& x, Vec3d* gradient) const {
  double value = sheets[0].Evaluate(x, gradient);
  Vec3d g;
  for (int k = 1; k < count; ++k) {
    const double f = sheets[static_cast<size_t>(k)].Evaluate(x, gradient ? &g : nullptr);
    if (take_max[static_cast<size_t>(k - 1)] ? f > value : f < value) {
      value = f;
      if (gradient) *gradient = g;
    }
  }
  return value;
}

std::optional<SharpFit> FitSharp(std::span<const Vec3d> points, std::span<const Vec3d> normals,
                                 std::span<const double> weights, double scale, const SharpParams& params,
                                 OrthogonalFitter& fitter) {
  const std::vector<uint32_t> members = WeightedMembers(weights);
  if (members.size() < 2) return std::nullopt;
  double smallest = 2;
  const auto [a, b] = WidestPair(normals, members, smallest);
  if (smallest >= params.edge_cos) return std::nullopt;
  const Vec3d na = normals[a], nb = normals[b];
  const Vec3d e = na.cross(nb);  // Not normalised, as in MPU: a wide pair tests stricter.
  double spread = 0;
  for (uint32_t i : members) spread = std::max(spread, std::abs(e.dot(normals[i])));
  SharpFit fit;
  std::array<std::vector<uint32_t>, kMaxSheets> groups;
  if (spread < params.corner_share) {
    fit.feature = Feature::kEdge;
    for (uint32_t i : members) groups[normals[i].dot(na) > normals[i].dot(nb) ? 0 : 1].push_back(i);
    fit.count = 2;
  } else {
    fit.feature = Feature::kCorner;
    const Vec3d n3 = e.normalized();
    for (uint32_t i : members) {
      const double da = normals[i].dot(na), db = normals[i].dot(nb), dc = std::abs(normals[i].dot(n3));
      groups[dc > std::max(da, db) ? 2 : da > db ? 0 : 1].push_back(i);
    }
    fit.count = 3;
    // The third cluster may itself hold an edge: a four-sheet corner.
    if (groups[2].size() >= 2) {
      double third_smallest = 2;
      const auto [c, d] = WidestPair(normals, groups[2], third_smallest);
      if (third_smallest < params.edge_cos) {
        std::vector<uint32_t> third = std::move(groups[2]);
        groups[2].clear();
        for (uint32_t i : third) groups[normals[i].dot(normals[c]) > normals[i].dot(normals[d]) ? 2 : 3].push_back(i);
        fit.count = 4;
      }
    }
  }
  if (!FitSheets(points, normals, weights, groups, scale, fitter, fit)) return std::nullopt;
  auto convex = [&](int i, int j) {
    return Convex(fit.sheets[static_cast<size_t>(i)], fit.sheets[static_cast<size_t>(j)]);
  };
  if (fit.count == 2) {
    fit.take_max[0] = convex(0, 1);
    return fit;
  }
  // All pairs alike: one operation throughout.
  if (bool all_convex = true; AllPairsAlike(fit, all_convex)) {
    fit.take_max.fill(all_convex);
    return fit;
  }
  if (fit.count == 4) return std::nullopt;  // Mixed four-sheet corners: MPU gives up too.
  // A saddle corner: the sheet k that relates alike to the other two goes last,
  // f = op_k(op_ij(f_i, f_j), f_k).
  for (int k = 0; k < 3; ++k) {
    const int i = (k + 1) % 3, j = (k + 2) % 3;
    if (convex(i, k) == convex(j, k) && convex(i, k) != convex(i, j)) {
      const std::array<Sheet, kMaxSheets> sheets = fit.sheets;
      fit.sheets[0] = sheets[static_cast<size_t>(i)];
      fit.sheets[1] = sheets[static_cast<size_t>(j)];
      fit.sheets[2] = sheets[static_cast<size_t>(k)];
      fit.take_max = {};
      fit.take_max[0] = convex(i, j);
      fit.take_max[1] = convex(i, k);
      return fit;
    }
  }
  return std::nullopt;
}

namespace {

// The cosine of half the angle whose cosine is `c`: how far apart two clusters of a clustering
// seeded at `c` must keep their normals.
double HalfAngleCos(double c) { return std::cos(0.5 * std::acos(std::clamp(c, -1.0, 1.0))); }

// Whether more than kMaxSheets of the members' normals lie pairwise more than `apart_cos` apart.
// Then no clustering into kMaxSheets clusters can be tight to half that angle (two of them share
// one); a smooth patch shows it after a few normals, well before a clustering would.
bool MoreDirectionsThanSheets(std::span<const Vec3d> normals, std::span<const uint32_t> members, double apart_cos) {
  std::array<Vec3d, kMaxSheets> found;
  size_t count = 0;
  for (uint32_t i : members) {
    const Vec3d& n = normals[i];
    if (std::any_of(found.begin(), found.begin() + static_cast<std::ptrdiff_t>(count),
                    [&](const Vec3d& f) { return n.dot(f) >= apart_cos; })) {
      continue;
    }
    if (count == found.size()) return true;
    found[count++] = n;
  }
  return false;
}

// One clustering at `seed_cos` of the members, seeded with the far-apart normals a and b.
std::optional<SharpFit> ClusterAt(std::span<const Vec3d> points, std::span<const Vec3d> normals,
                                  std::span<const double> weights, std::span<const uint32_t> members, uint32_t a,
                                  uint32_t b, double scale, double seed_cos, OrthogonalFitter& fitter) {
  std::vector<Vec3d> seeds{normals[a], normals[b]};
  // nearest[i]: the largest cosine from member i's normal to a seed so far.
  std::vector<double> nearest(members.size());
  for (size_t i = 0; i < members.size(); ++i) {
    nearest[i] = std::max(normals[members[i]].dot(seeds[0]), normals[members[i]].dot(seeds[1]));
  }
  while (static_cast<int>(seeds.size()) < kMaxSheets) {
    const size_t far = static_cast<size_t>(std::min_element(nearest.begin(), nearest.end()) - nearest.begin());
    if (nearest[far] >= seed_cos) break;
    seeds.push_back(normals[members[far]]);
    for (size_t i = 0; i < members.size(); ++i)
      nearest[i] = std::max(nearest[i], normals[members[i]].dot(seeds.back()));
  }
  // One k-means step: each sheet's normal becomes its members' mean, then the members are
  // assigned again (a seed taken at a rounded edge's point would otherwise pull its neighbours).
  std::vector<std::vector<uint32_t>> groups(seeds.size());
  auto assign = [&] {
    for (auto& g : groups) g.clear();
    for (uint32_t i : members) {
      size_t best = 0;
      for (size_t k = 1; k < seeds.size(); ++k) {
        if (normals[i].dot(seeds[k]) > normals[i].dot(seeds[best])) best = k;
      }
      groups[best].push_back(i);
    }
  };
  assign();
  for (size_t k = 0; k < seeds.size(); ++k) {
    Vec3d mean = Vec3d::Zero();
    for (uint32_t i : groups[k]) mean += weights[i] * normals[i];
    if (mean.norm() > 0) seeds[k] = mean.normalized();
  }
  assign();
  // Faces, not a curved patch cut into pieces: every cluster's normals lie within a quarter of
  // the seeding angle of their mean, and no normal of one cluster comes within half of it of
  // another cluster's (a smooth patch's normals vary without such a gap).
  const double seed_angle = std::acos(std::clamp(seed_cos, -1.0, 1.0));
  const double tight_cos = std::cos(0.25 * seed_angle), gap_cos = HalfAngleCos(seed_cos);
  for (size_t k = 0; k < groups.size(); ++k) {
    Vec3d mean = Vec3d::Zero();
    for (uint32_t i : groups[k]) mean += normals[i];
    if (!(mean.norm() > 0)) return std::nullopt;
    mean.normalize();
    for (uint32_t i : groups[k]) {
      if (normals[i].dot(mean) < tight_cos) return std::nullopt;
    }
  }
  for (size_t k = 0; k < groups.size(); ++k) {
    for (size_t l = k + 1; l < groups.size(); ++l) {
      for (uint32_t i : groups[k]) {
        for (uint32_t j : groups[l]) {
          if (normals[i].dot(normals[j]) > gap_cos) return std::nullopt;
        }
      }
    }
  }
  SharpFit fit;
  fit.count = static_cast<int>(seeds.size());
  fit.feature = fit.count == 2 ? Feature::kEdge : Feature::kCorner;
  bool all_convex = true;
  if (!FitSheets(points, normals, weights, groups, scale, fitter, fit) || !AllPairsAlike(fit, all_convex)) {
    return std::nullopt;
  }
  fit.take_max.fill(all_convex);
  return fit;
}

}  // namespace

void FitSharpClusters(std::span<const Vec3d> points, std::span<const Vec3d> normals, std::span<const double> weights,
                      double scale, std::span<const double> seed_cos, const std::function<bool(const SharpFit&)>& take,
                      OrthogonalFitter& fitter) {
  const std::vector<uint32_t> members = WeightedMembers(weights);
  if (members.size() < 2) return;
  // Two far-apart normals in O(n), not the widest pair's O(n²): the one farthest from the mean,
  // then the one farthest from it (farthest-point seeding needs no more).
  Vec3d mean = Vec3d::Zero();
  for (uint32_t i : members) mean += normals[i];
  auto farthest_from = [&](const Vec3d& d) {
    return *std::min_element(members.begin(), members.end(),
                             [&](uint32_t i, uint32_t j) { return normals[i].dot(d) < normals[j].dot(d); });
  };
  const uint32_t a = farthest_from(mean), b = farthest_from(normals[a]);
  const double smallest = normals[a].dot(normals[b]);
  for (const double c : seed_cos) {
    if (smallest >= c) continue;
    // Its clusters must be tight to a quarter of the seeding angle: normals half of it apart
    // cannot share one.
    if (MoreDirectionsThanSheets(normals, members, HalfAngleCos(c))) continue;
    std::optional<SharpFit> fit = ClusterAt(points, normals, weights, members, a, b, scale, c, fitter);
    if (fit && take(*fit)) return;
  }
}

}  // namespace lsqsurf::pu
