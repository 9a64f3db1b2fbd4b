#include "worker/core/mesh_metrics.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>
#include <tuple>

#include "worker/core/geometry.h"
#include "worker/core/parallel.h"

namespace lsqsurf::core {
namespace {

uint32_t FindRoot(std::vector<uint32_t>& parent, uint32_t x) {
  while (parent[x] != x) x = parent[x] = parent[parent[x]];
  return x;
}

// Drops the vertices no face uses, keeping the others in their order with their normals and
// attributes, and renumbers the faces.
void DropUnusedVertices(TriangleMesh& mesh) {
  std::vector<uint32_t> index(mesh.vertices.size(), UINT32_MAX);
  for (const Triangle& t : mesh.faces) {
    for (uint32_t v : t) index[v] = 0;
  }
  uint32_t count = 0;
  for (size_t v = 0; v < mesh.vertices.size(); ++v) {
    if (index[v] == UINT32_MAX) continue;
    index[v] = count;
    mesh.vertices[count] = mesh.vertices[v];
    if (!mesh.normals.empty()) mesh.normals[count] = mesh.normals[v];
    for (ScalarAttribute& a : mesh.vertex_attributes) a.values[count] = a.values[v];
    ++count;
  }
  mesh.vertices.resize(count);
  if (!mesh.normals.empty()) mesh.normals.resize(count);
  for (ScalarAttribute& a : mesh.vertex_attributes) a.values.resize(count);
  for (Triangle& t : mesh.faces) {
    for (uint32_t& v : t) v = index[v];
  }
}

// Vertex indices ordered by position (lexicographic), so equal positions are adjacent.
std::vector<uint32_t> OrderByPosition(const std::vector<Vec3f>& v) {
  std::vector<uint32_t> order(v.size());
  std::iota(order.begin(), order.end(), 0u);
  std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) {
    return std::tie(v[a].x(), v[a].y(), v[a].z()) < std::tie(v[b].x(), v[b].y(), v[b].z());
  });
  return order;
}

}  // namespace

TriangleMesh WeldByPosition(const TriangleMesh& mesh) {
  const std::vector<uint32_t> order = OrderByPosition(mesh.vertices);
  std::vector<uint32_t> remap(mesh.vertices.size());
  TriangleMesh out;
  for (size_t i = 0; i < order.size(); ++i) {
    if (i == 0 || mesh.vertices[order[i]] != mesh.vertices[order[i - 1]]) {
      out.vertices.push_back(mesh.vertices[order[i]]);
    }
    remap[order[i]] = static_cast<uint32_t>(out.vertices.size() - 1);
  }
  out.faces.reserve(mesh.faces.size());
  for (const Triangle& f : mesh.faces) out.faces.push_back({remap[f[0]], remap[f[1]], remap[f[2]]});
  return out;
}

void IncidentFaces(const TriangleMesh& mesh, std::vector<uint32_t>& start, std::vector<uint32_t>& incident,
                   uint32_t first) {
  const size_t rows = mesh.vertices.size() - std::min<size_t>(first, mesh.vertices.size());
  start.assign(rows + 1, 0);
  for (const Triangle& t : mesh.faces) {
    for (uint32_t v : t) {
      if (v >= first) ++start[v - first + 1];
    }
  }
  for (size_t i = 0; i < rows; ++i) start[i + 1] += start[i];
  incident.resize(start[rows]);
  std::vector<uint32_t> cursor(start.begin(), start.end() - 1);
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    for (uint32_t v : mesh.faces[f]) {
      if (v >= first) incident[cursor[v - first]++] = f;
    }
  }
}

int64_t MergeCoincidentVertices(TriangleMesh& mesh) {
  const std::vector<uint32_t> order = OrderByPosition(mesh.vertices);
  std::vector<uint32_t> first(mesh.vertices.size());
  for (size_t i = 0; i < order.size(); ++i) {
    const bool same = i > 0 && mesh.vertices[order[i]] == mesh.vertices[order[i - 1]];
    first[order[i]] = same ? first[order[i - 1]] : order[i];
  }
  // Faces by their sorted vertex triple. A collapsed face goes; of the faces on one triple,
  // opposite orientations cancel (a pair encloses nothing) and one of the rest stays.
  std::vector<std::pair<std::array<uint32_t, 3>, uint32_t>> sorted;
  sorted.reserve(mesh.faces.size());
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    Triangle& t = mesh.faces[f];
    for (uint32_t& v : t) v = first[v];
    std::array<uint32_t, 3> key = t;
    std::sort(key.begin(), key.end());
    sorted.emplace_back(key, f);
  }
  std::sort(sorted.begin(), sorted.end());
  // +1 where the face runs through its sorted triple in cyclic order, −1 where against it.
  auto orientation = [&](uint32_t f) {
    const Triangle& t = mesh.faces[f];
    const size_t lowest = static_cast<size_t>(std::min_element(t.begin(), t.end()) - t.begin());
    return t[(lowest + 1) % 3] < t[(lowest + 2) % 3] ? 1 : -1;
  };
  std::vector<char> drop(mesh.faces.size(), 1);
  for (size_t i = 0; i < sorted.size();) {
    size_t j = i;
    while (j < sorted.size() && sorted[j].first == sorted[i].first) ++j;
    const auto& key = sorted[i].first;
    if (key[0] != key[1] && key[1] != key[2]) {
      int sum = 0;
      for (size_t k = i; k < j; ++k) sum += orientation(sorted[k].second);
      for (size_t k = i; k < j && sum != 0; ++k) {
        if (orientation(sorted[k].second) == (sum > 0 ? 1 : -1)) {
          drop[sorted[k].second] = 0;
          break;
        }
      }
    }
    i = j;
  }
  int64_t dropped = 0;
  size_t kept = 0;
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    if (drop[f]) {
      ++dropped;
      continue;
    }
    mesh.faces[kept++] = mesh.faces[f];
  }
  mesh.faces.resize(kept);
  DropUnusedVertices(mesh);
  return dropped;
}

int64_t CountDistinctPositions(const std::vector<Vec3f>& positions) {
  const std::vector<uint32_t> order = OrderByPosition(positions);
  int64_t distinct = 0;
  for (size_t i = 0; i < order.size(); ++i) {
    if (i == 0 || positions[order[i]] != positions[order[i - 1]]) ++distinct;
  }
  return distinct;
}

uint32_t TopologyAccumulator::Root(uint32_t v) {
  while (parent_[v] != v) v = parent_[v] = parent_[parent_[v]];  // Path halving.
  return v;
}

void TopologyAccumulator::AddFace(int64_t a, int64_t b, int64_t c) {
  ++faces_;
  const std::array<uint32_t, 3> corner = {static_cast<uint32_t>(a), static_cast<uint32_t>(b), static_cast<uint32_t>(c)};
  if (a == b || b == c || a == c) ++degenerate_;
  for (const uint32_t v : corner) {
    if (v >= parent_.size()) parent_.resize(std::max<size_t>(v + 1, parent_.size() * 3 / 2), UINT32_MAX);
    if (parent_[v] == UINT32_MAX) parent_[v] = v;
  }
  for (int i = 0; i < 3; ++i) {
    const uint32_t from = corner[static_cast<size_t>(i)], to = corner[static_cast<size_t>((i + 1) % 3)];
    const uint32_t lo = std::min(from, to), hi = std::max(from, to);
    const uint64_t key = uint64_t{lo} << 32 | hi;
    const auto [it, opened] = open_.try_emplace(key, from < to);
    if (!opened) {  // Its second face: closed, consistently oriented if it ran the other way.
      misoriented_ += it->second == (from < to);
      ++closed_;
      open_.erase(it);
    }
    parent_[Root(from)] = Root(to);
  }
}

MeshTopology TopologyAccumulator::Result() {
  MeshTopology t;
  t.faces = faces_;
  t.boundary_edges = static_cast<int64_t>(open_.size());
  t.edges = closed_ + t.boundary_edges;
  t.misoriented_edges = misoriented_;
  t.degenerate_faces = degenerate_;
  for (uint32_t v = 0; v < parent_.size(); ++v) {
    if (parent_[v] == UINT32_MAX) continue;
    ++t.vertices;
    t.components += Root(v) == v;
  }
  return t;
}

MeshTopology AnalyzeTopology(const TriangleMesh& mesh) {
  MeshTopology t;
  t.faces = static_cast<int64_t>(mesh.faces.size());
  // (min vertex, max vertex, face, forward?) per face side.
  struct HalfEdge {
    uint32_t lo, hi, face;
    bool forward;
  };
  std::vector<HalfEdge> half;
  half.reserve(mesh.faces.size() * 3);
  std::vector<char> used(mesh.vertices.size(), 0);
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    const Triangle& tri = mesh.faces[f];
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2]) ++t.degenerate_faces;
    for (int i = 0; i < 3; ++i) {
      const uint32_t a = tri[static_cast<size_t>(i)], b = tri[static_cast<size_t>((i + 1) % 3)];
      assert(a < mesh.vertices.size() && b < mesh.vertices.size());
      used[a] = 1;
      half.push_back({std::min(a, b), std::max(a, b), f, a < b});
    }
  }
  t.vertices = std::count(used.begin(), used.end(), 1);
  std::sort(half.begin(), half.end(),
            [](const HalfEdge& x, const HalfEdge& y) { return std::tie(x.lo, x.hi) < std::tie(y.lo, y.hi); });
  std::vector<uint32_t> parent(mesh.faces.size());
  std::iota(parent.begin(), parent.end(), 0u);
  std::vector<std::pair<uint32_t, uint32_t>> boundary;
  std::vector<uint32_t> open_faces;  // The face of each boundary edge.
  for (size_t i = 0; i < half.size();) {
    size_t j = i;
    while (j < half.size() && half[j].lo == half[i].lo && half[j].hi == half[i].hi) ++j;
    const size_t count = j - i;
    ++t.edges;
    if (count == 1)
      ++t.boundary_edges, boundary.push_back({half[i].lo, half[i].hi}), open_faces.push_back(half[i].face);
    if (count >= 3) ++t.non_manifold_edges;
    if (count == 2 && half[i].forward == half[i + 1].forward) ++t.misoriented_edges;
    const uint32_t first_face = half[i].face;
    for (auto it = half.begin() + static_cast<std::ptrdiff_t>(i) + 1;
         it != half.begin() + static_cast<std::ptrdiff_t>(j); ++it) {
      parent[FindRoot(parent, it->face)] = FindRoot(parent, first_face);
    }
    i = j;
  }
  for (uint32_t f = 0; f < parent.size(); ++f) t.components += FindRoot(parent, f) == f;
  {
    std::vector<char> open(mesh.faces.size(), 0);  // Per component root: it has a boundary edge.
    int64_t open_components = 0;
    for (const uint32_t f : open_faces) {
      char& flag = open[FindRoot(parent, f)];
      open_components += flag == 0, flag = 1;
    }
    t.closed_components = t.components - open_components;
  }
  if (!boundary.empty()) {
    std::vector<uint32_t> loop_of(mesh.vertices.size());
    std::iota(loop_of.begin(), loop_of.end(), 0u);
    for (const auto& [a, b] : boundary) loop_of[FindRoot(loop_of, a)] = FindRoot(loop_of, b);
    for (const auto& [a, b] : boundary) {
      // Each loop once, by its root (marked 2 in `used`).
      for (const uint32_t v : {a, b}) {
        const uint32_t root = FindRoot(loop_of, v);
        if (used[root] != 2) used[root] = 2, ++t.boundary_loops;
      }
    }
  }
  return t;
}

double EnclosedVolume(const TriangleMesh& mesh) {
  double six_v = 0;
  for (const Triangle& f : mesh.faces) {
    const Vec3d a = mesh.vertices[f[0]].cast<double>();
    const Vec3d b = mesh.vertices[f[1]].cast<double>();
    const Vec3d c = mesh.vertices[f[2]].cast<double>();
    six_v += a.dot(b.cross(c));
  }
  return six_v / 6.0;
}

double FaceArea(const TriangleMesh& mesh, const Triangle& face) {
  const Vec3d a = mesh.vertices[face[0]].cast<double>();
  return 0.5 * (mesh.vertices[face[1]].cast<double>() - a).cross(mesh.vertices[face[2]].cast<double>() - a).norm();
}

double SurfaceArea(const TriangleMesh& mesh) {
  double area = 0;
  for (const Triangle& f : mesh.faces) area += FaceArea(mesh, f);
  return area;
}

TriangleQuality MeasureTriangleQuality(const TriangleMesh& mesh) {
  TriangleQuality q;
  if (mesh.faces.empty()) return q;
  std::vector<double> min_angles, aspect;
  min_angles.reserve(mesh.faces.size());
  aspect.reserve(mesh.faces.size());
  for (const Triangle& f : mesh.faces) {
    const std::array<Vec3d, 3> p = {mesh.vertices[f[0]].cast<double>(), mesh.vertices[f[1]].cast<double>(),
                                    mesh.vertices[f[2]].cast<double>()};
    std::array<double, 3> edge;  // edge[i] is opposite p[i].
    for (size_t i = 0; i < 3; ++i) edge[i] = (p[(i + 1) % 3] - p[(i + 2) % 3]).norm();
    const double area = 0.5 * (p[1] - p[0]).cross(p[2] - p[0]).norm();
    double smallest = 180;
    for (size_t i = 0; i < 3; ++i) {
      const Vec3d u = p[(i + 1) % 3] - p[i], v = p[(i + 2) % 3] - p[i];
      smallest = std::min(smallest, std::atan2(u.cross(v).norm(), u.dot(v)) * 180 / std::numbers::pi);
    }
    min_angles.push_back(smallest);
    const double longest = std::max({edge[0], edge[1], edge[2]});
    aspect.push_back(area > 0 ? longest * (edge[0] + edge[1] + edge[2]) / (4 * std::sqrt(3.0) * area)
                              : std::numeric_limits<double>::infinity());
    const auto bin = static_cast<size_t>(std::clamp(static_cast<int>(smallest / TriangleQuality::kBinDegrees), 0,
                                                    static_cast<int>(q.min_angle_histogram.size()) - 1));
    ++q.min_angle_histogram[bin];
  }
  auto quantile = [](std::vector<double>& v, double share) {
    const auto k = static_cast<int64_t>(share * static_cast<double>(v.size() - 1));
    std::nth_element(v.begin(), v.begin() + k, v.end());
    return v[static_cast<size_t>(k)];
  };
  q.min_angle_p1 = quantile(min_angles, 0.01);
  q.min_angle_median = quantile(min_angles, 0.5);
  q.aspect_ratio_p99 = quantile(aspect, 0.99);
  return q;
}

std::vector<char> FacesOfComponents(const TriangleMesh& mesh, const std::function<bool(const Box3&)>& pick,
                                    int64_t& picked) {
  std::vector<uint32_t> parent(mesh.vertices.size());
  std::iota(parent.begin(), parent.end(), 0u);
  for (const Triangle& t : mesh.faces) {
    parent[FindRoot(parent, t[1])] = FindRoot(parent, t[0]);
    parent[FindRoot(parent, t[2])] = FindRoot(parent, t[0]);
  }
  std::vector<Box3> box(mesh.vertices.size());
  for (const Triangle& t : mesh.faces) {
    for (uint32_t v : t) box[FindRoot(parent, v)].extend(mesh.vertices[v].cast<double>());
  }
  picked = 0;
  std::vector<char> root_picked(mesh.vertices.size(), 0);
  for (uint32_t v = 0; v < parent.size(); ++v) {
    if (parent[v] == v && !box[v].isEmpty() && pick(box[v])) {
      root_picked[v] = 1;
      ++picked;
    }
  }
  std::vector<char> faces(mesh.faces.size(), 0);
  if (picked == 0) return faces;
  for (size_t f = 0; f < mesh.faces.size(); ++f) faces[f] = root_picked[FindRoot(parent, mesh.faces[f][0])];
  return faces;
}

std::vector<uint32_t> ComponentOfFaces(const TriangleMesh& mesh, uint32_t& count) {
  // One node per distinct position.
  const std::vector<uint32_t> order = PositionOrder(mesh.vertices);
  std::vector<uint32_t> node(mesh.vertices.size(), 0);
  uint32_t nodes = 0;
  for (size_t r = 0; r < order.size(); ++r) {
    if (r > 0 && mesh.vertices[order[r]] != mesh.vertices[order[r - 1]]) ++nodes;
    node[order[r]] = nodes;
  }
  std::vector<uint32_t> parent(order.empty() ? 0 : nodes + 1);
  std::iota(parent.begin(), parent.end(), 0u);
  for (const Triangle& t : mesh.faces) {
    parent[FindRoot(parent, node[t[1]])] = FindRoot(parent, node[t[0]]);
    parent[FindRoot(parent, node[t[2]])] = FindRoot(parent, node[t[0]]);
  }
  std::vector<uint32_t> label_of_root(parent.size(), UINT32_MAX);
  std::vector<uint32_t> label(mesh.faces.size());
  count = 0;
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    uint32_t& l = label_of_root[FindRoot(parent, node[mesh.faces[f][0]])];
    if (l == UINT32_MAX) l = count++;
    label[f] = l;
  }
  return label;
}

std::vector<double> WindingNumbers(const TriangleMesh& mesh, std::span<const char> faces,
                                   std::span<const Vec3d> probes) {
  // Fixed blocks summed in order: a parallel reduction's own split would change the rounding.
  constexpr size_t kBlock = 16384;
  const size_t blocks = (mesh.faces.size() + kBlock - 1) / kBlock;
  std::vector<double> partial(blocks * probes.size(), 0.0);
  (void)ParallelFor(partial.size(), 1, [&](size_t begin, size_t end) {
    for (size_t task = begin; task < end; ++task) {
      const Vec3d& p = probes[task / blocks];
      const size_t b = task % blocks;
      double sum = 0;
      for (size_t f = b * kBlock; f < std::min(mesh.faces.size(), (b + 1) * kBlock); ++f) {
        if (!faces[f]) continue;
        const Triangle& t = mesh.faces[f];
        const Vec3d a = mesh.vertices[t[0]].cast<double>() - p, u = mesh.vertices[t[1]].cast<double>() - p,
                    w = mesh.vertices[t[2]].cast<double>() - p;
        // The triangle's solid angle (Van Oosterom and Strackee 1983).
        const double la = a.norm(), lu = u.norm(), lw = w.norm();
        const double det = a.dot(u.cross(w));
        const double den = la * lu * lw + a.dot(u) * lw + a.dot(w) * lu + u.dot(w) * la;
        sum += 2 * std::atan2(det, den);
      }
      partial[task] = sum;
    }
  });
  std::vector<double> winding(probes.size(), 0.0);
  for (size_t task = 0; task < partial.size(); ++task) winding[task / blocks] += partial[task];
  for (double& w : winding) w /= 4 * std::numbers::pi;
  return winding;
}

void RemoveFaces(TriangleMesh& mesh, std::span<const char> drop) {
  size_t kept = 0;
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    if (!drop[f]) mesh.faces[kept++] = mesh.faces[f];
  }
  mesh.faces.resize(kept);
  DropUnusedVertices(mesh);
}

int64_t RemoveSmallComponents(TriangleMesh& mesh, double min_diagonal) {
  int64_t removed = 0;
  const std::vector<char> small = FacesOfComponents(
      mesh, [&](const Box3& box) { return Diagonal(box) < min_diagonal; }, removed);
  if (removed == 0) return 0;
  RemoveFaces(mesh, small);
  return removed;
}

}  // namespace lsqsurf::core
