#include "worker/core/geometry.h"

#include <tbb/parallel_sort.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <unordered_map>
#include <utility>

namespace lsqsurf::core {

Box3 BoundingBox(std::span<const Vec3f> points) {
  Box3 box;  // Default-constructed AlignedBox is empty.
  for (const Vec3f& p : points) box.extend(p.cast<double>());
  return box;
}

double Diagonal(const Box3& box) { return box.isEmpty() ? 0.0 : box.diagonal().norm(); }

namespace {

// Spreads the low 21 bits of `v` so that two zero bits follow each one.
uint64_t SpreadBits(uint64_t v) {
  v &= 0x1fffff;
  v = (v | v << 32) & 0x1f00000000ffffull;
  v = (v | v << 16) & 0x1f0000ff0000ffull;
  v = (v | v << 8) & 0x100f00f00f00f00full;
  v = (v | v << 4) & 0x10c30c30c30c30c3ull;
  v = (v | v << 2) & 0x1249249249249249ull;
  return v;
}

}  // namespace

std::vector<uint32_t> MortonOrder(std::span<const Vec3f> points) {
  const Box3 box = BoundingBox(points);
  const double extent = box.isEmpty() ? 1.0 : std::max(box.sizes().maxCoeff(), 1e-30);
  const double scale = static_cast<double>((1 << 21) - 1) / extent;
  std::vector<std::pair<uint64_t, uint32_t>> keyed(points.size());
  for (size_t i = 0; i < points.size(); ++i) {
    const Vec3d g = (points[i].cast<double>() - box.min()) * scale;
    keyed[i] = {SpreadBits(static_cast<uint64_t>(g.x())) | SpreadBits(static_cast<uint64_t>(g.y())) << 1 |
                    SpreadBits(static_cast<uint64_t>(g.z())) << 2,
                static_cast<uint32_t>(i)};
  }
  tbb::parallel_sort(keyed.begin(), keyed.end());
  std::vector<uint32_t> order(points.size());
  for (size_t i = 0; i < keyed.size(); ++i) order[i] = keyed[i].second;
  return order;
}

std::vector<uint32_t> PositionOrder(std::span<const Vec3f> p) {
  std::vector<uint32_t> order(p.size());
  std::iota(order.begin(), order.end(), 0u);
  tbb::parallel_sort(order.begin(), order.end(), [&p](uint32_t a, uint32_t b) {
    if (p[a].x() != p[b].x()) return p[a].x() < p[b].x();
    if (p[a].y() != p[b].y()) return p[a].y() < p[b].y();
    if (p[a].z() != p[b].z()) return p[a].z() < p[b].z();
    return a < b;
  });
  return order;
}

namespace {

bool LexLess(const Vec3f& a, const Vec3f& b) {
  return std::lexicographical_compare(a.data(), a.data() + 3, b.data(), b.data() + 3);
}

// Vertices at one position (a crease's split copies, a seam's twins) ordered by what lies around
// them rather than by their old index: their normal, then the positions of their faces' other
// corners (in orientation order, the faces sorted), so that the order is the surface's own.
void OrderCoincidentVertices(const TriangleMesh& mesh, std::vector<uint32_t>& order) {
  const auto& p = mesh.vertices;
  std::vector<uint8_t> tied(p.size(), 0);
  bool any = false;
  for (size_t r = 1; r < order.size(); ++r) {
    if (p[order[r]] == p[order[r - 1]]) tied[order[r]] = tied[order[r - 1]] = 1, any = true;
  }
  if (!any) return;
  using Corner = std::pair<Vec3f, Vec3f>;
  std::unordered_map<uint32_t, std::vector<Corner>> around;
  for (const Triangle& t : mesh.faces) {
    for (int c = 0; c < 3; ++c) {
      if (tied[t[c]]) around[t[c]].emplace_back(p[t[(c + 1) % 3]], p[t[(c + 2) % 3]]);
    }
  }
  auto corner_less = [](const Corner& a, const Corner& b) {
    if (a.first != b.first) return LexLess(a.first, b.first);
    return LexLess(a.second, b.second);
  };
  for (auto& [v, corners] : around) std::ranges::sort(corners, corner_less);
  const bool has_normals = mesh.normals.size() == p.size();
  auto less = [&](uint32_t a, uint32_t b) {
    if (has_normals && mesh.normals[a] != mesh.normals[b]) return LexLess(mesh.normals[a], mesh.normals[b]);
    const auto& ca = around[a];
    const auto& cb = around[b];
    if (std::ranges::lexicographical_compare(ca, cb, corner_less)) return true;
    if (std::ranges::lexicographical_compare(cb, ca, corner_less)) return false;
    return a < b;  // Indistinguishable: either order gives the same mesh.
  };
  for (size_t begin = 0; begin < order.size();) {
    size_t end = begin + 1;
    while (end < order.size() && p[order[end]] == p[order[begin]]) ++end;
    if (end - begin > 1) std::sort(order.begin() + begin, order.begin() + end, less);
    begin = end;
  }
}

}  // namespace

void SortMeshByPosition(TriangleMesh& mesh) {
  std::vector<uint32_t> order = PositionOrder(mesh.vertices);
  OrderCoincidentVertices(mesh, order);
  std::vector<uint32_t> rank(order.size());
  for (uint32_t r = 0; r < order.size(); ++r) rank[order[r]] = r;
  auto gather = [&order](auto& values) {
    if (values.size() != order.size()) return;
    std::remove_reference_t<decltype(values)> sorted(values.size());
    for (size_t r = 0; r < order.size(); ++r) sorted[r] = values[order[r]];
    values = std::move(sorted);
  };
  gather(mesh.vertices);
  gather(mesh.normals);
  for (ScalarAttribute& a : mesh.vertex_attributes) gather(a.values);
  for (Triangle& t : mesh.faces) {
    t = {rank[t[0]], rank[t[1]], rank[t[2]]};
    // Rotated to start at its lowest vertex; the orientation stays.
    std::rotate(t.begin(), std::min_element(t.begin(), t.end()), t.end());
  }
  tbb::parallel_sort(mesh.faces.begin(), mesh.faces.end());
}

size_t RemoveDuplicatePoints(PointCloud& cloud) {
  const size_t n = cloud.size();
  if (n < 2) return 0;
  // Sorted by position, ties by index: each run of equal positions starts at its first point.
  const std::vector<uint32_t> order = PositionOrder(cloud.positions);
  const auto& p = cloud.positions;
  std::vector<uint8_t> repeated(n, 0);
  size_t removed = 0;
  for (size_t t = 1; t < n; ++t) {
    if (p[order[t]] == p[order[t - 1]]) {
      repeated[order[t]] = 1;
      ++removed;
    }
  }
  if (removed == 0) return 0;
  RemovePoints(cloud, repeated);
  return removed;
}

std::array<const ScalarAttribute*, 3> ColourChannels(std::span<const ScalarAttribute> attributes, size_t count) {
  std::array<const ScalarAttribute*, 3> channels = {nullptr, nullptr, nullptr};
  for (const ScalarAttribute& a : attributes) {
    for (size_t c = 0; c < 3; ++c) {
      if (a.name == kColourChannels[c] && a.values.size() == count && channels[c] == nullptr) channels[c] = &a;
    }
  }
  if (channels[0] == nullptr || channels[1] == nullptr || channels[2] == nullptr) return {nullptr, nullptr, nullptr};
  return channels;
}

uint32_t PackedColour(const std::array<const ScalarAttribute*, 3>& channels, size_t i) {
  uint32_t bits = 0;
  for (const ScalarAttribute* c : channels) {
    bits = (bits << 8) | static_cast<uint32_t>(std::clamp(std::round(c->values[i]), 0.0f, 255.0f));
  }
  return bits;
}

void AppendCloud(PointCloud& cloud, const PointCloud& more) {
  std::erase_if(cloud.attributes, [&](ScalarAttribute& kept) {
    for (const ScalarAttribute& a : more.attributes) {
      if (a.name != kept.name || a.values.size() != more.size()) continue;
      kept.values.insert(kept.values.end(), a.values.begin(), a.values.end());
      return false;
    }
    return true;
  });
  cloud.positions.insert(cloud.positions.end(), more.positions.begin(), more.positions.end());
  cloud.normals.insert(cloud.normals.end(), more.normals.begin(), more.normals.end());
}

void RemovePoints(PointCloud& cloud, const std::vector<uint8_t>& remove) {
  const size_t n = cloud.size();
  auto compact = [&](auto& values) {
    if (values.size() != n) return;
    size_t kept = 0;
    for (size_t i = 0; i < n; ++i) {
      if (!remove[i]) values[kept++] = values[i];
    }
    values.resize(kept);
  };
  compact(cloud.normals);
  for (ScalarAttribute& attribute : cloud.attributes) compact(attribute.values);
  compact(cloud.positions);
}

int64_t FindNonFinite(std::span<const Vec3f> points) {
  for (size_t i = 0; i < points.size(); ++i) {
    if (!points[i].allFinite()) return static_cast<int64_t>(i);
  }
  return -1;
}

}  // namespace lsqsurf::core
