#include "worker/core/normals.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <optional>
#include <queue>

#include "absl/container/flat_hash_set.h"
#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::core {

absl::Status Validate(const NormalEstimationParams& params) {
  if (params.neighbors < 3 || params.neighbors > 128) {
    return absl::InvalidArgumentError("normal_neighbors must be between 3 and 128");
  }
  if (params.scales < 1 || params.scales > 4) {
    return absl::InvalidArgumentError("normal estimation scales must be between 1 and 4");
  }
  if (!(params.max_hidden_share >= 0 && params.max_hidden_share <= 1)) {
    return absl::InvalidArgumentError("the largest hidden share of a viewpoint must be between 0 and 1");
  }
  for (uint32_t s : params.station) {
    if (s >= params.viewpoints.size()) {
      return absl::InvalidArgumentError(StrCat("a point's scan is ", s, " but the viewpoint gives only ",
                                               params.viewpoints.size(), " sensor positions"));
    }
  }
  return absl::OkStatus();
}

namespace {

// The k nearest points of a clean scan lie flatter than this (λ₀ / Σλ; the spread along the
// normal under 8 % of the spread across): larger neighbourhoods are not looked at there, which
// keeps clean clouds at the cost of one small query per point.
constexpr double kFlatEnough = 3e-3;

// The position of the sensor that saw point `i`.
const Vec3d& SensorOf(const NormalEstimationParams& params, size_t i) {
  return params.viewpoints[params.station.empty() ? 0 : params.station[i]];
}

// A component's points vote for the sign that turns them toward their sensors (set aside for
// hiding too many points, but still where most of them were seen from): where at least this
// share more of them vote one way than the other, the component takes that sign.
constexpr double kDecisiveVote = 0.5;

// Per component, whether its sign was decided by such a vote (and turned so).
std::vector<char> TurnTowardSensorsByVote(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                          const std::vector<uint32_t>& component, uint32_t components,
                                          std::vector<Vec3f>& normals) {
  std::vector<char> decided(components, 0);
  if (params.viewpoints.empty()) return decided;
  std::vector<double> votes(components, 0.0), count(components, 0.0);
  for (size_t i = 0; i < points.size(); ++i) {
    const Vec3d& eye = SensorOf(params, i);
    votes[component[i]] += normals[i].cast<double>().dot(eye - points[i].cast<double>()) >= 0 ? 1.0 : -1.0;
    count[component[i]] += 1.0;
  }
  for (uint32_t c = 0; c < components; ++c) decided[c] = std::abs(votes[c]) >= kDecisiveVote * count[c];
  for (size_t i = 0; i < points.size(); ++i) {
    if (decided[component[i]] && votes[component[i]] < 0) normals[i] = -normals[i];
  }
  return decided;
}

// Outward per component (those `decided` leaves): the sign that makes the normals point away from
// its centroid.
void PointAwayFromCentroids(std::span<const Vec3f> points, const std::vector<uint32_t>& component, uint32_t components,
                            const std::vector<char>& decided, std::vector<Vec3f>& normals) {
  const size_t n = points.size();
  std::vector<Vec3d> centroid(components, Vec3d::Zero());
  std::vector<double> count(components, 0.0), flux(components, 0.0);
  for (size_t i = 0; i < n; ++i) {
    centroid[component[i]] += points[i].cast<double>();
    count[component[i]] += 1.0;
  }
  for (uint32_t c = 0; c < components; ++c) centroid[c] /= count[c];
  for (size_t i = 0; i < n; ++i) {
    flux[component[i]] += (points[i].cast<double>() - centroid[component[i]]).dot(normals[i].cast<double>());
  }
  for (size_t i = 0; i < n; ++i) {
    if (!decided[component[i]] && flux[component[i]] < 0) normals[i] = -normals[i];
  }
}

// Looks at the first `from_size`, 2 × `from_size` − 1, … points of the neighbourhood (closest
// first, the point itself among them; all of them last) and keeps in `normal` and `variation`
// the least-variance direction of the flattest, where it is flatter than `variation` already is
// (ties keep the smaller). The sums run once over the points, about `centre` for precision.
void KeepFlattest(std::span<const Vec3f> points, const Vec3f& centre, const std::vector<Neighbor>& neighbourhood,
                  size_t from_size, Vec3f& normal, double& variation) {
  Vec3d sum = Vec3d::Zero();
  Eigen::Matrix3d outer = Eigen::Matrix3d::Zero();
  size_t next_size = std::min(from_size, neighbourhood.size());
  for (size_t q = 0; q < neighbourhood.size(); ++q) {
    const Vec3d d = (points[neighbourhood[q].index] - centre).cast<double>();
    sum += d;
    outer += d * d.transpose();
    if (q + 1 != next_size) continue;
    const double count = static_cast<double>(q + 1);
    const Eigen::Matrix3d covariance = outer / count - (sum / count) * (sum / count).transpose();
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
    eig.computeDirect(covariance);
    const double total = eig.eigenvalues().sum();
    const double flatness = total > 0 ? eig.eigenvalues()(0) / total : 0.0;
    if (flatness < variation) {
      variation = flatness;
      normal = eig.eigenvectors().col(0).cast<float>().normalized();
    }
    next_size = std::min(2 * (next_size - 1) + 1, neighbourhood.size());
  }
}

// A thin wall's two faces (or a narrow slot's two sides) closer than the spacing of the points
// share neighbours: their normals are parallel, so the spanning tree would copy one face's sign
// onto the other, the cheapest step of all. A closed surface's two layers always face opposite
// ways (away from each other across a wall, towards each other across a slot), so such steps
// must flip the sign instead; which of the two readings holds is left to the outward step.
// Each point looks at the offsets of its graph neighbours along its normal: where they fall into
// two flat layers parted by a clear gap, the neighbours beyond the gap whose normals are parallel
// are across. Curved, noisy or creased neighbourhoods spread their offsets and show no such gap.
constexpr double kLayerGapToSpread = 3.0;   // The gap is this many times either layer's spread,
constexpr double kLayerGapToRadius = 0.05;  // and this share of the neighbourhood's radius at least.
constexpr float kParallelCosine = 0.8f;     // Normals within 37° count as parallel.
constexpr float kSteepShare = 0.25f;        // Steep: rising a quarter of its length along both normals.

constexpr int kVotePasses = 3;  // Each pass shrinks a wrongly turned patch by about one ring.

enum EdgeKind : uint8_t { kAlong = 0, kAcross = 1, kDoubtful = 2 };

// Kinds of the directed graph edges i → knn[i * k + j], from i's side.
void ClassifyEdges(std::span<const Vec3f> points, const std::vector<Vec3f>& normals, const std::vector<uint32_t>& knn,
                   size_t k, size_t begin, size_t end, std::vector<uint8_t>& kinds, std::vector<Vec3f>& mid_gap) {
  std::vector<std::pair<float, uint32_t>> offsets;
  for (size_t i = begin; i < end; ++i) {
    offsets.assign(1, {0.0f, UINT32_MAX});
    float radius = 0;
    for (size_t j = 0; j < k; ++j) {
      const uint32_t q = knn[i * k + j];
      const Vec3f d = points[q] - points[i];
      radius = std::max(radius, d.norm());
      if (q != i) offsets.push_back({d.dot(normals[i]), static_cast<uint32_t>(j)});
    }
    std::sort(offsets.begin(), offsets.end());
    size_t split = 0;  // The widest gap lies between offsets[split - 1] and offsets[split].
    float gap = 0;
    for (size_t q = 1; q < offsets.size(); ++q) {
      if (offsets[q].first - offsets[q - 1].first > gap) {
        gap = offsets[q].first - offsets[q - 1].first;
        split = q;
      }
    }
    size_t own = 0;
    while (offsets[own].second != UINT32_MAX) ++own;
    const bool own_below = own < split;
    const size_t own_count = own_below ? split : offsets.size() - split;
    // No gap at all (split 0) where every neighbour lies in the point's plane, as on a flat face.
    const float low_spread = split > 0 ? offsets[split - 1].first - offsets.front().first : 0.0f;
    const float high_spread = offsets.back().first - offsets[split].first;
    const bool layered = split > 0 && own_count >= 4 && offsets.size() - own_count >= 2 &&
                         gap > kLayerGapToSpread * std::max(low_spread, high_spread) &&
                         gap > kLayerGapToRadius * radius;
    if (layered) mid_gap[i] = 0.5f * (offsets[split - 1].first + offsets[split].first) * normals[i];
    for (size_t q = 0; q < offsets.size(); ++q) {
      if (offsets[q].second == UINT32_MAX) continue;
      const size_t j = offsets[q].second;
      const uint32_t other = knn[i * k + j];
      const Vec3f d = points[other] - points[i];
      const bool parallel = std::abs(normals[i].dot(normals[other])) > kParallelCosine;
      uint8_t kind = kAlong;
      if (layered && (q < split) != own_below && parallel) {
        kind = kAcross;
      } else if (parallel && std::abs(d.dot(normals[i])) > kSteepShare * d.norm() &&
                 std::abs(d.dot(normals[other])) > kSteepShare * d.norm()) {
        kind = kDoubtful;  // Possibly across a wall that this point cannot see as one: no vote.
      }
      kinds[i * k + j] = kind;
    }
  }
}

// Kinds of the graph's steps (kinds[i * k + j] for i → knn[i * k + j]) and the bridges: points
// beside layered ones that are not layered themselves.
absl::Status FindLayers(std::span<const Vec3f> points, const std::vector<Vec3f>& normals,
                        const std::vector<uint32_t>& knn, size_t k, JobContext& ctx, std::vector<uint8_t>& kinds,
                        std::vector<uint8_t>& bridge) {
  const size_t n = points.size();
  std::vector<Vec3f> mid_gap(n, Vec3f::Zero());  // From a layered point to the middle of its gap.
  absl::Status status = ParallelFor(
      n, 1024, [&](size_t begin, size_t end) { ClassifyEdges(points, normals, knn, k, begin, end, kinds, mid_gap); },
      &ctx);
  if (!status.ok()) return status;
  // A step is across only if both ends see it so; a gap seen from one end only is a chance
  // pattern of the samples (a curved sheet's outliers), and the step is doubtful.
  std::vector<uint8_t> layered(n);
  for (size_t i = 0; i < n; ++i) layered[i] = mid_gap[i] != Vec3f::Zero();
  for (size_t i = 0; i < n; ++i) {
    for (size_t j = 0; j < k; ++j) {
      if (kinds[i * k + j] != kAcross) continue;
      const uint32_t other = knn[i * k + j];
      const Vec3f& middle = mid_gap[other];
      if (!layered[other] || (points[i] - points[other]).dot(middle) < middle.squaredNorm()) {
        kinds[i * k + j] = kDoubtful;
      }
    }
  }
  // A point beside layered ones that is not layered itself lies where the layers meet (the rim of
  // a wall, the floor of a slot) or blur into each other: the tree takes its steps last.
  for (size_t i = 0; i < n; ++i) {
    if (layered[i]) continue;
    for (size_t j = 0; j < k && !bridge[i]; ++j) bridge[i] = layered[knn[i * k + j]];
  }
  return absl::OkStatus();
}

absl::Status VoteSigns(const std::vector<uint64_t>& offset, const std::vector<uint32_t>& adjacency,
                       const std::vector<uint8_t>& adjacency_kind, const std::vector<uint8_t>& bridge, JobContext& ctx,
                       std::vector<Vec3f>& normals) {
  const size_t n = normals.size();
  // The tree reaches each point along one step only, and the doubtful steps it took last may
  // disagree with most of a point's neighbours: let the trusted steps of every point vote.
  for (int pass = 0; pass < kVotePasses; ++pass) {
    const std::vector<Vec3f> voted = normals;
    const absl::Status status = ParallelFor(
        n, 4096,
        [&](size_t begin, size_t end) {
          for (size_t i = begin; i < end; ++i) {
            float agreement = 0;
            for (uint64_t e = offset[i]; e < offset[i + 1]; ++e) {
              const uint32_t j = adjacency[e];
              if (adjacency_kind[e] == kDoubtful || bridge[j]) continue;
              const float dot = voted[i].dot(voted[j]);
              agreement += (dot > 0) != (adjacency_kind[e] == kAcross) ? std::abs(dot) : -std::abs(dot);
            }
            if (agreement < 0) normals[i] = -voted[i];
          }
        },
        &ctx);
    if (!status.ok()) return status;
  }
  return absl::OkStatus();
}

// Normals seen from nearer edge-on than this cosine (about 80° from the line of sight) are
// not turned by the viewpoint alone.
constexpr double kGrazingCosine = 0.17;

// Turns each normal toward its sensor; those seen nearly edge-on take the sign their
// confidently turned graph neighbours agree on, and keep the sensor's where none has one.
absl::Status OrientTowardViewpoint(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                   const std::vector<uint32_t>& knn, size_t k, JobContext& ctx,
                                   std::vector<Vec3f>& normals) {
  const size_t n = points.size();
  std::vector<uint8_t> confident(n, 0);
  absl::Status status = ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) {
          const Vec3d& viewpoint = SensorOf(params, i);
          const Vec3d sight = viewpoint - points[i].cast<double>();
          const double length = sight.norm();
          const double cosine = length > 0 ? normals[i].cast<double>().dot(sight) / length : 1.0;
          if (cosine < 0) normals[i] = -normals[i];
          confident[i] = std::abs(cosine) > kGrazingCosine;
        }
      },
      &ctx);
  if (!status.ok()) return status;
  std::vector<uint8_t> flip(n, 0);
  status = ParallelFor(
      n, 4096,
      [&](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) {
          if (confident[i]) continue;
          double agreement = 0;
          for (size_t j = 0; j < k; ++j) {
            const uint32_t other = knn[i * k + j];
            if (other != i && confident[other]) agreement += normals[other].dot(normals[i]);
          }
          flip[i] = agreement < 0;
        }
      },
      &ctx);
  if (!status.ok()) return status;
  for (size_t i = 0; i < n; ++i) {
    if (flip[i]) normals[i] = -normals[i];
  }
  return absl::OkStatus();
}

// The share of a sample of the points (up to kHiddenSample, spread over the cloud) whose line of
// sight toward its sensor meets another point: a cell of a grid of twice the median spacing
// that holds points, within the cloud's box, at least 4 reaches along the ray and 3 off the
// point's tangent plane, the reach being the distance to its k-th neighbour (a ray grazing its
// own surface stays near it for a while; a sensor's noise grows with range, and so does its
// spacing: the far wall of a simulated room seen by a depth camera hid 17 % of the points at
// twice the median spacing, 1 % at the reach).
constexpr size_t kHiddenSample = 4096;
constexpr size_t kMostRaySteps = 8192;

absl::StatusOr<double> HiddenShare(std::span<const Vec3f> points, const std::vector<Vec3f>& normals,
                                   const NormalEstimationParams& params, const std::vector<uint32_t>& knn, size_t k,
                                   JobContext& ctx) {
  const size_t n = points.size();
  const size_t stride = std::max<size_t>(1, n / kHiddenSample);
  std::vector<double> nearest;
  for (size_t i = 0; i < n; i += stride) {
    // Repeated positions are no spacing (a job removes them first; a caller may not have).
    if (const double d = (points[knn[i * k]] - points[i]).cast<double>().norm(); d > 0) nearest.push_back(d);
  }
  if (nearest.empty()) return 0.0;
  std::nth_element(nearest.begin(), nearest.begin() + static_cast<std::ptrdiff_t>(nearest.size() / 2), nearest.end());
  const double spacing = nearest[nearest.size() / 2];
  const Box3 box = BoundingBox(points);
  constexpr int64_t kAxisCells = int64_t{1} << 21;  // Three axes in one 64-bit key.
  const double cell = std::max(2 * spacing, box.sizes().maxCoeff() / static_cast<double>(kAxisCells - 1));
  if (!(cell > 0)) return 0.0;
  auto key_of = [&](const Vec3d& x) -> std::optional<uint64_t> {
    const Eigen::Array3d c = ((x - box.min()) / cell).array().floor();
    if ((c < 0).any() || (c >= static_cast<double>(kAxisCells)).any()) return std::nullopt;
    return (static_cast<uint64_t>(c.x()) << 42) | (static_cast<uint64_t>(c.y()) << 21) | static_cast<uint64_t>(c.z());
  };
  absl::flat_hash_set<uint64_t> occupied;
  occupied.reserve(n);
  for (const Vec3f& p : points) occupied.insert(*key_of(p.cast<double>()));
  const size_t samples = (n + stride - 1) / stride;
  std::vector<uint8_t> hidden(samples, 0);
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      samples, 64,
      [&](size_t begin, size_t end) {
        for (size_t s = begin; s < end; ++s) {
          const size_t i = s * stride;
          const Vec3d p = points[i].cast<double>();
          const Vec3d sight = SensorOf(params, i) - p;
          const double distance = sight.norm();
          if (!(distance > 0)) continue;
          const Vec3d u = sight / distance;
          double leave = distance - 2 * spacing;  // Where the ray leaves the box, or short of the sensor.
          for (int a = 0; a < 3; ++a) {
            if (u[a] > 1e-12) leave = std::min(leave, (box.max()[a] - p[a]) / u[a]);
            if (u[a] < -1e-12) leave = std::min(leave, (box.min()[a] - p[a]) / u[a]);
          }
          const double off_plane = std::abs(u.dot(normals[i].cast<double>()));
          const double reach = std::max(spacing, (points[knn[i * k + k - 1]] - points[i]).cast<double>().norm());
          const double start = std::max(4 * reach, 3 * reach / std::max(off_plane, 1e-3));
          const double step = std::max(cell / 2, (leave - start) / static_cast<double>(kMostRaySteps));
          for (double t = start; t < leave && !hidden[s]; t += step) {
            const std::optional<uint64_t> key = key_of(p + t * u);
            hidden[s] = key.has_value() && occupied.contains(*key);
          }
        }
      },
      &ctx));
  return static_cast<double>(std::count(hidden.begin(), hidden.end(), 1)) / static_cast<double>(samples);
}

// Each point's least-variance direction, of the flattest of its neighbourhoods (no sign yet),
// and its k nearest other points (the graph orientation walks).
absl::Status UnsignedNormals(std::span<const Vec3f> points, const NormalEstimationParams& params, size_t k,
                             JobContext& ctx, std::vector<uint32_t>& knn, std::vector<Vec3f>& normals) {
  const size_t n = points.size();
  const size_t largest = std::min<size_t>(k << (params.scales - 1), n - 1);
  SubContext pca_ctx(ctx, "estimating normals", 0.0, 0.6);
  KdTree tree(points);
  return ParallelFor(
      n, 1024,
      [&](size_t begin, size_t end) {
        std::vector<Neighbor> nn;
        for (size_t i = begin; i < end; ++i) {
          tree.Knn(points[i], k + 1, nn);
          double variation = std::numeric_limits<double>::infinity();
          normals[i] = Vec3f::UnitZ();
          KeepFlattest(points, points[i], nn, k + 1, normals[i], variation);
          if (largest > k && variation > kFlatEnough) {
            tree.Knn(points[i], largest + 1, nn);
            KeepFlattest(points, points[i], nn, 2 * k + 1, normals[i], variation);
          }
          // Skip the query point itself (normally first); keep exactly k graph neighbours.
          size_t written = 0;
          for (const Neighbor& q : nn) {
            if (q.index == i || written == k) continue;
            knn[i * k + written++] = q.index;
          }
          while (written < k) knn[i * k + written++] = static_cast<uint32_t>(i);
        }
      },
      &ctx, [&](double f) { pca_ctx.Report(f); });
}

}  // namespace

absl::StatusOr<std::vector<Vec3f>> EstimateNormals(std::span<const Vec3f> points, const NormalEstimationParams& params,
                                                   JobContext& ctx, NormalOrientation* orientation) {
  NormalOrientation decided;
  if (orientation == nullptr) orientation = &decided;
  *orientation = {};
  if (absl::Status s = Validate(params); !s.ok()) return s;
  const size_t n = points.size();
  if (n < 3) return absl::InvalidArgumentError("normal estimation needs at least 3 points");
  const size_t k = std::min<size_t>(static_cast<size_t>(params.neighbors), n - 1);
  std::vector<uint32_t> knn(n * k);
  std::vector<Vec3f> normals(n);
  LSQSURF_RETURN_IF_ERROR(UnsignedNormals(points, params, k, ctx, knn, normals));
  if (!params.viewpoints.empty()) {
    if (!params.station.empty() && params.station.size() != n) {
      return absl::InvalidArgumentError(StrCat(params.station.size(), " scan indices for ", n, " points"));
    }
    auto hidden = HiddenShare(points, normals, params, knn, k, ctx);
    if (!hidden.ok()) return hidden.status();
    orientation->hidden_share = *hidden;
    orientation->toward_viewpoints = *hidden <= params.max_hidden_share;
  }
  if (orientation->toward_viewpoints) {
    SubContext orient_ctx(ctx, "orienting normals toward the sensor", 0.6, 1.0);
    LSQSURF_RETURN_IF_ERROR(OrientTowardViewpoint(points, params, knn, k, orient_ctx, normals));
    orient_ctx.Report(1.0);
    return normals;
  }
  std::vector<uint8_t> kinds(n * k, kAlong), bridge(n, 0);
  if (absl::Status layers = FindLayers(points, normals, knn, k, ctx, kinds, bridge); !layers.ok()) return layers;

  // Symmetric adjacency (CSR) of the k-NN graph: orientation must be able to cross an edge
  // from either end.
  SubContext orient_ctx(ctx, "orienting normals", 0.6, 1.0);
  std::vector<uint32_t> degree(n + 1, 0);
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < k; ++j) {
      ++degree[i];
      ++degree[knn[i * k + j]];
    }
  std::vector<uint64_t> offset(n + 1, 0);
  for (size_t i = 0; i < n; ++i) offset[i + 1] = offset[i] + degree[i];
  std::vector<uint32_t> adjacency(offset[n]);
  std::vector<uint8_t> adjacency_kind(offset[n]);
  std::vector<uint64_t> cursor(offset.begin(), offset.end() - 1);
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < k; ++j) {
      const uint32_t other = knn[i * k + j];
      adjacency_kind[cursor[i]] = adjacency_kind[cursor[other]] = kinds[i * k + j];
      adjacency[cursor[i]++] = other;
      adjacency[cursor[other]++] = static_cast<uint32_t>(i);
    }
  knn.clear();
  knn.shrink_to_fit();
  kinds.clear();
  kinds.shrink_to_fit();

  // Prim's algorithm, one tree per connected component, seeded at the highest point whose
  // normal is turned towards +z (Hoppe's choice).
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return points[a].z() > points[b].z(); });
  std::vector<uint32_t> component(n, UINT32_MAX);
  struct Edge {
    float cost;
    uint32_t from, to;
    bool across;
    bool operator>(const Edge& o) const { return cost > o.cost; }
  };
  std::priority_queue<Edge, std::vector<Edge>, std::greater<>> heap;
  uint32_t components = 0;
  size_t visited = 0;
  for (uint32_t seed : order) {
    if (component[seed] != UINT32_MAX) continue;
    if (normals[seed].z() < 0) normals[seed] = -normals[seed];
    const uint32_t c = components++;
    component[seed] = c;
    auto push_edges = [&](uint32_t from) {
      for (uint64_t e = offset[from]; e < offset[from + 1]; ++e) {
        const uint32_t to = adjacency[e];
        if (component[to] != UINT32_MAX) continue;
        const float bend = 1.0f - std::abs(normals[from].dot(normals[to]));
        heap.push({bridge[from] || bridge[to] ? bend + 1.0f : bend, from, to, adjacency_kind[e] == kAcross});
      }
    };
    push_edges(seed);
    while (!heap.empty()) {
      const Edge edge = heap.top();
      heap.pop();
      if (component[edge.to] != UINT32_MAX) continue;
      component[edge.to] = c;
      if ((normals[edge.from].dot(normals[edge.to]) < 0) != edge.across) normals[edge.to] = -normals[edge.to];
      push_edges(edge.to);
      if ((++visited & 0xFFFF) == 0) {
        if (ctx.IsCancelled()) return absl::CancelledError("cancelled by request");
        orient_ctx.Report(static_cast<double>(visited) / static_cast<double>(n));
      }
    }
  }

  const absl::Status status = VoteSigns(offset, adjacency, adjacency_kind, bridge, ctx, normals);
  if (!status.ok()) return status;

  const std::vector<char> voted = TurnTowardSensorsByVote(points, params, component, components, normals);
  PointAwayFromCentroids(points, component, components, voted, normals);
  orient_ctx.Report(1.0);
  return normals;
}

}  // namespace lsqsurf::core
