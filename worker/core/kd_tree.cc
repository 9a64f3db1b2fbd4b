#include "worker/core/kd_tree.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <nanoflann.hpp>

#include "worker/core/parallel.h"

namespace lsqsurf::core {
namespace {

// nanoflann's dataset interface over a span of Vec3f.
struct SpanAdaptor {
  std::span<const Vec3f> points;
  size_t kdtree_get_point_count() const { return points.size(); }
  float kdtree_get_pt(size_t i, size_t dim) const { return points[i][static_cast<int>(dim)]; }
  template <class Box>
  bool kdtree_get_bbox(Box&) const {
    return false;
  }
};

using Tree =
    nanoflann::KDTreeSingleIndexAdaptor<nanoflann::L2_Simple_Adaptor<float, SpanAdaptor>, SpanAdaptor, 3, uint32_t>;

}  // namespace

struct KdTree::Index {
  explicit Index(std::span<const Vec3f> pts)
      : adaptor{pts}, tree(3, adaptor, nanoflann::KDTreeSingleIndexAdaptorParams(16)) {
    // An empty tree cannot be built; queries on it return nothing.
    if (!pts.empty()) tree.buildIndex();
  }
  SpanAdaptor adaptor;
  Tree tree;
};

KdTree::KdTree(std::span<const Vec3f> points) : points_(points), index_(std::make_unique<Index>(points)) {}

KdTree::~KdTree() = default;

void KdTree::Knn(const Vec3f& query, size_t k, std::vector<Neighbor>& out) const {
  out.clear();
  k = std::min(k, points_.size());
  if (k == 0) return;
  std::vector<uint32_t> idx(k);
  std::vector<float> d2(k);
  nanoflann::KNNResultSet<float, uint32_t> result(k);
  result.init(idx.data(), d2.data());
  index_->tree.findNeighbors(result, query.data(), nanoflann::SearchParams());
  const size_t found = result.size();
  out.reserve(found);
  for (size_t i = 0; i < found; ++i) out.push_back({idx[i], d2[i]});
}

void KdTree::Radius(const Vec3f& query, float radius, std::vector<Neighbor>& out) const {
  out.clear();
  if (points_.empty()) return;
  // nanoflann 1.4 fills pairs of (index, squared distance); the radius it takes is squared.
  // The buffer is per thread so that hot evaluation loops do not allocate.
  thread_local std::vector<std::pair<uint32_t, float>> matches;
  nanoflann::SearchParams params;
  params.sorted = false;
  index_->tree.radiusSearch(query.data(), radius * radius, matches, params);
  out.reserve(matches.size());
  for (const auto& [i, d2] : matches) out.push_back({i, d2});
}

Neighbor KdTree::Nearest(const Vec3f& query) const {
  uint32_t idx = 0;
  float d2 = 0;
  nanoflann::KNNResultSet<float, uint32_t> result(1);
  result.init(&idx, &d2);
  index_->tree.findNeighbors(result, query.data(), nanoflann::SearchParams());
  return {idx, d2};
}

double MeanNearestNeighborDistance(const KdTree& tree) {
  const size_t n = tree.size();
  if (n < 2) return 0.0;
  std::vector<double> partial(n, 0.0);
  (void)ParallelFor(n, 2048, [&](size_t begin, size_t end) {
    std::vector<Neighbor> nn;
    for (size_t i = begin; i < end; ++i) {
      tree.Knn(tree.points()[i], 2, nn);
      partial[i] = nn.size() > 1 ? std::sqrt(static_cast<double>(nn[1].distance2)) : 0.0;
    }
  });
  double sum = 0;
  for (double d : partial) sum += d;
  return sum / static_cast<double>(n);
}

}  // namespace lsqsurf::core
