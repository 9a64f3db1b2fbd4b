#include "worker/core/surface_distance.h"

#include <algorithm>
#include <cmath>
#include <numeric>

#include "worker/core/parallel.h"
#include "worker/core/sampling.h"

namespace lsqsurf::core {
namespace {

constexpr uint32_t kLeafSize = 4;

// Closest point on triangle abc to p (Ericson, Real-Time Collision Detection, §5.1.5):
// classify p against the Voronoi regions of the vertices, edges and face.
Vec3d ClosestOnTriangle(const Vec3d& p, const Vec3d& a, const Vec3d& b, const Vec3d& c) {
  const Vec3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Vec3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + (d1 / (d1 - d3)) * ab;
  const Vec3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + (d2 / (d2 - d6)) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  }
  const double denom = va + vb + vc;
  if (denom == 0) return a;  // Degenerate triangle: any vertex is as good as another.
  return a + ab * (vb / denom) + ac * (vc / denom);
}

Vec3d FaceNormal(const TriangleMesh& m, uint32_t f) {
  const auto& t = m.faces[f];
  const Vec3d a = m.vertices[t[0]].cast<double>();
  const Vec3d n = (m.vertices[t[1]].cast<double>() - a).cross(m.vertices[t[2]].cast<double>() - a);
  const double len = n.norm();
  return len > 0 ? Vec3d(n / len) : Vec3d::Zero();
}

}  // namespace

struct TriangleTree::Node {
  Box3 box;
  uint32_t begin = 0, end = 0;   // Leaf: range in `order_`.
  uint32_t left = 0, right = 0;  // Inner: child node indices (0 = none; the root is never a child).
};

TriangleTree::TriangleTree(const TriangleMesh& mesh) : mesh_(mesh) {
  order_.resize(mesh.faces.size());
  std::iota(order_.begin(), order_.end(), 0u);
  nodes_.reserve(2 * mesh.faces.size() / kLeafSize + 2);
  nodes_.emplace_back();
  if (!order_.empty()) Build(0, 0, static_cast<uint32_t>(order_.size()), 0);
}

TriangleTree::~TriangleTree() = default;

void TriangleTree::Build(uint32_t node, uint32_t begin, uint32_t end, int depth) {
  Box3 box, centroids;
  for (uint32_t i = begin; i < end; ++i) {
    const auto& f = mesh_.faces[order_[i]];
    Vec3d c = Vec3d::Zero();
    for (uint32_t v : f) {
      box.extend(mesh_.vertices[v].cast<double>());
      c += mesh_.vertices[v].cast<double>() / 3.0;
    }
    centroids.extend(c);
  }
  nodes_[node].box = box;
  nodes_[node].begin = begin;
  nodes_[node].end = end;
  if (end - begin <= kLeafSize || depth > 60) return;
  int axis = 0;
  centroids.sizes().maxCoeff(&axis);
  const uint32_t mid = begin + (end - begin) / 2;
  std::nth_element(order_.begin() + begin, order_.begin() + mid, order_.begin() + end, [&](uint32_t x, uint32_t y) {
    auto key = [&](uint32_t f) {
      const auto& t = mesh_.faces[f];
      return mesh_.vertices[t[0]][axis] + mesh_.vertices[t[1]][axis] + mesh_.vertices[t[2]][axis];
    };
    return key(x) < key(y);
  });
  const auto left = static_cast<uint32_t>(nodes_.size());
  nodes_.emplace_back();
  const auto right = static_cast<uint32_t>(nodes_.size());
  nodes_.emplace_back();
  nodes_[node].left = left;
  nodes_[node].right = right;
  Build(left, begin, mid, depth + 1);
  Build(right, mid, end, depth + 1);
}

TriangleTree::Hit TriangleTree::Closest(const Vec3d& query) const {
  Hit best;
  best.distance2 = std::numeric_limits<double>::infinity();
  uint32_t stack[128];
  int top = 0;
  stack[top++] = 0;
  while (top > 0) {
    const Node& node = nodes_[stack[--top]];
    if (node.box.squaredExteriorDistance(query) >= best.distance2) continue;
    if (node.left == 0) {
      for (uint32_t i = node.begin; i < node.end; ++i) {
        const auto& f = mesh_.faces[order_[i]];
        const Vec3d p = ClosestOnTriangle(query, mesh_.vertices[f[0]].cast<double>(),
                                          mesh_.vertices[f[1]].cast<double>(), mesh_.vertices[f[2]].cast<double>());
        const double d2 = (p - query).squaredNorm();
        if (d2 < best.distance2) best = {d2, p, order_[i]};
      }
      continue;
    }
    // Push the farther child first so the nearer one is searched first and prunes more.
    const double dl = nodes_[node.left].box.squaredExteriorDistance(query);
    const double dr = nodes_[node.right].box.squaredExteriorDistance(query);
    if (dl < dr) {
      stack[top++] = node.right;
      stack[top++] = node.left;
    } else {
      stack[top++] = node.left;
      stack[top++] = node.right;
    }
  }
  return best;
}

absl::StatusOr<CompareResult> CompareMeshes(const TriangleMesh& reference, const TriangleMesh& candidate,
                                            const CompareParams& params, JobContext& ctx) {
  if (reference.faces.empty()) return absl::InvalidArgumentError("the reference mesh has no faces");
  if (candidate.faces.empty()) return absl::InvalidArgumentError("the candidate mesh has no faces");
  CompareResult r;
  r.diagonal = Diagonal(BoundingBox(reference.vertices));
  if (!(r.diagonal > 0)) return absl::InvalidArgumentError("the reference mesh has zero extent");

  struct OneSided {
    double mean = 0, max = 0, vertex_max = 0, cos_sum = 0, far = 0;
  };
  auto one_sided = [&](const TriangleMesh& from, const TriangleMesh& to, uint64_t seed, double begin,
                       double end) -> absl::StatusOr<OneSided> {
    SubContext sub(ctx, "measuring distances", begin, end);
    const auto samples = SampleSurface(from, params.samples, seed, false);
    TriangleTree tree(to);
    std::vector<double> dist(samples.size()), cosine(samples.size());
    absl::Status s = ParallelFor(
        samples.size(), 1024,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i) {
            const auto hit = tree.Closest(samples[i].position.cast<double>());
            dist[i] = std::sqrt(hit.distance2);
            cosine[i] = std::abs(FaceNormal(from, samples[i].face).dot(FaceNormal(to, hit.face)));
          }
        },
        &ctx, [&](double f) { sub.Report(f); });
    if (!s.ok()) return s;
    // The vertices too, for a maximum of their own: area samples almost never land on a corner's
    // tip, where a surface that rounds it off is farthest from the other.
    std::vector<double> vertex_distance(from.vertices.size());
    s = ParallelFor(
        from.vertices.size(), 1024,
        [&](size_t b, size_t e) {
          for (size_t i = b; i < e; ++i)
            vertex_distance[i] = std::sqrt(tree.Closest(from.vertices[i].cast<double>()).distance2);
        },
        &ctx);
    if (!s.ok()) return s;
    OneSided o;
    for (double d : vertex_distance) o.vertex_max = std::max(o.vertex_max, d);
    const double far_threshold = 1e-3 * r.diagonal;
    for (size_t i = 0; i < dist.size(); ++i) {
      o.mean += dist[i];
      o.max = std::max(o.max, dist[i]);
      o.cos_sum += cosine[i];
      o.far += dist[i] > far_threshold ? 1.0 : 0.0;
    }
    const auto n = static_cast<double>(std::max<size_t>(1, dist.size()));
    o.mean /= n;
    o.cos_sum /= n;
    o.far /= n;
    return o;
  };
  auto ref_to_cand = one_sided(reference, candidate, params.seed, 0.0, 0.5);
  if (!ref_to_cand.ok()) return ref_to_cand.status();
  auto cand_to_ref = one_sided(candidate, reference, params.seed + 1, 0.5, 1.0);
  if (!cand_to_ref.ok()) return cand_to_ref.status();
  r.mean_ref_to_cand = ref_to_cand->mean / r.diagonal;
  r.mean_cand_to_ref = cand_to_ref->mean / r.diagonal;
  r.chamfer = 0.5 * (r.mean_ref_to_cand + r.mean_cand_to_ref);
  r.hausdorff = std::max(ref_to_cand->max, cand_to_ref->max) / r.diagonal;
  r.hausdorff_with_vertices =
      std::max({ref_to_cand->max, cand_to_ref->max, ref_to_cand->vertex_max, cand_to_ref->vertex_max}) / r.diagonal;
  r.normal_consistency = 0.5 * (ref_to_cand->cos_sum + cand_to_ref->cos_sum);
  r.far_fraction = ref_to_cand->far;
  return r;
}

}  // namespace lsqsurf::core
