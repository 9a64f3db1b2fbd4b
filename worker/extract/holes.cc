#include "worker/extract/holes.h"

#include <algorithm>
#include <array>
#include <limits>
#include <span>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/mesh_metrics.h"

namespace lsqsurf::extract::internal {
namespace {

using core::Triangle;
using core::Vec3f;

uint64_t Undirected(uint32_t a, uint32_t b) { return a < b ? (uint64_t{a} << 32) | b : (uint64_t{b} << 32) | a; }

// The least-area triangulation of the loop (Barequet & Sharir's dynamic programme): cost[i][j]
// is the least area of a fan over loop[i..j] closed by the chord (i, j). Chords that are edges of
// the mesh already are not used. Appends the triangles; false where no triangulation avoids them.
template <typename IsEdge>
bool TriangulateLoop(const std::vector<uint32_t>& loop, const std::vector<Vec3f>& vertices, const IsEdge& is_edge,
                     std::vector<Triangle>& out) {
  const size_t n = loop.size();
  constexpr double kNone = std::numeric_limits<double>::infinity();
  std::vector<double> cost(n * n, kNone);
  std::vector<uint32_t> split(n * n, 0);
  auto at = [n](size_t i, size_t j) { return i * n + j; };
  for (size_t i = 0; i + 1 < n; ++i) cost[at(i, i + 1)] = 0;
  for (size_t span = 2; span < n; ++span) {
    for (size_t i = 0; i + span < n; ++i) {
      const size_t j = i + span;
      // (0, n−1) is a border edge; every other chord must be new.
      if (!(i == 0 && j == n - 1) && is_edge(loop[i], loop[j])) continue;
      const Vec3f &a = vertices[loop[i]], &c = vertices[loop[j]];
      for (size_t k = i + 1; k < j; ++k) {
        const double sides = cost[at(i, k)] + cost[at(k, j)];
        if (sides == kNone) continue;
        const double area = 0.5 * static_cast<double>((vertices[loop[k]] - a).cross(c - a).norm());
        if (sides + area < cost[at(i, j)]) cost[at(i, j)] = sides + area, split[at(i, j)] = static_cast<uint32_t>(k);
      }
    }
  }
  if (cost[at(0, n - 1)] == kNone) return false;
  std::vector<std::pair<size_t, size_t>> pending = {{0, n - 1}};
  while (!pending.empty()) {
    const auto [i, j] = pending.back();
    pending.pop_back();
    if (j - i < 2) continue;
    const size_t k = split[at(i, j)];
    out.push_back({loop[i], loop[k], loop[j]});
    pending.push_back({i, k});
    pending.push_back({k, j});
  }
  return true;
}

}  // namespace

int64_t FillSmallHoles(core::TriangleMesh& mesh, int max_edges) {
  max_edges = std::min(max_edges, kMaxHoleEdges);
  if (max_edges < 3 || mesh.faces.empty()) return 0;
  // A closed mesh (the common case) pays one pass over its faces.
  uint64_t unmatched = 0;
  for (const Triangle& t : mesh.faces) unmatched += core::UnmatchedEdgeSum(t);
  if (unmatched == 0) return 0;
  // Each vertex's faces: a twin edge or a chord is looked up among a few faces, in linear time
  // and memory (a hash of every edge cost a large mesh 10 % more time for the few holes it has).
  std::vector<uint32_t> start, incident;
  core::IncidentFaces(mesh, start, incident);
  auto faces_of = [&](uint32_t v) {
    return std::span<const uint32_t>(incident.data() + start[v], incident.data() + start[v + 1]);
  };
  auto runs = [&](uint32_t face, uint32_t a, uint32_t b) {  // Whether `face` goes from a to b.
    const Triangle& t = mesh.faces[face];
    return (t[0] == a && t[1] == b) || (t[1] == a && t[2] == b) || (t[2] == a && t[0] == b);
  };
  auto has = [&](uint32_t face, uint32_t v) {
    return std::ranges::find(mesh.faces[face], v) != mesh.faces[face].end();
  };
  // A hole's loop runs against the faces around it: border edge a→b gives the filling b→a.
  constexpr uint32_t kNoVertex = std::numeric_limits<uint32_t>::max();
  absl::flat_hash_map<uint32_t, uint32_t> next;  // Along the holes' loops.
  absl::flat_hash_set<uint32_t> tangled;         // Vertices no loop may pass.
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    const Triangle& t = mesh.faces[f];
    for (size_t s = 0; s < 3; ++s) {
      const uint32_t a = t[s], b = t[(s + 1) % 3];
      if (a == b) continue;
      int twins = 0, along = 0;
      for (uint32_t g : faces_of(a)) twins += runs(g, b, a), along += runs(g, a, b);
      if (along > 1) tangled.insert(a), tangled.insert(b);
      if (twins == 0 && !next.try_emplace(b, a).second) tangled.insert(b);
    }
  }
  if (next.empty()) return 0;
  // Border vertices at one position: welded, their borders may close each other.
  absl::flat_hash_map<std::array<float, 3>, uint32_t> at;
  for (const auto& [v, unused] : next) {
    const Vec3f& p = mesh.vertices[v];
    const auto [it, fresh] = at.try_emplace(std::array<float, 3>{p.x(), p.y(), p.z()}, v);
    if (!fresh) tangled.insert(v), tangled.insert(it->second);
  }
  absl::flat_hash_set<uint64_t> added;  // Edges of the fillings so far.
  auto is_edge = [&](uint32_t a, uint32_t b) {
    return std::ranges::any_of(faces_of(a), [&](uint32_t g) { return has(g, b); }) || added.contains(Undirected(a, b));
  };
  int64_t filled = 0;
  absl::flat_hash_set<uint32_t> visited;
  std::vector<uint32_t> loop;
  std::vector<Triangle> patch;
  for (const auto& [first, unused] : next) {
    if (visited.contains(first)) continue;
    loop.clear();
    bool closed = false, usable = true;
    for (uint32_t v = first; v != kNoVertex;) {
      if (!visited.insert(v).second) {
        closed = v == first;
        break;
      }
      loop.push_back(v);
      usable &= !tangled.contains(v) && loop.size() <= static_cast<size_t>(max_edges);
      const auto it = next.find(v);
      v = it == next.end() ? kNoVertex : it->second;
    }
    if (!closed || !usable || loop.size() < 3) continue;
    // Three border edges around a face of their own: a lone triangle, not a hole.
    if (loop.size() == 3 &&
        std::ranges::any_of(faces_of(loop[0]), [&](uint32_t g) { return has(g, loop[1]) && has(g, loop[2]); })) {
      continue;
    }
    patch.clear();
    if (!TriangulateLoop(loop, mesh.vertices, is_edge, patch)) continue;
    for (const Triangle& t : patch) {
      for (size_t s = 0; s < 3; ++s) added.insert(Undirected(t[s], t[(s + 1) % 3]));
      mesh.faces.push_back(t);
    }
    ++filled;
  }
  return filled;
}

}  // namespace lsqsurf::extract::internal
