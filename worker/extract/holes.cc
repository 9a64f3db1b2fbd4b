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

constexpr uint32_t kNoVertex = std::numeric_limits<uint32_t>::max();

uint64_t Undirected(uint32_t a, uint32_t b) { return a < b ? (uint64_t{a} << 32) | b : (uint64_t{b} << 32) | a; }
uint64_t Directed(uint32_t a, uint32_t b) { return (uint64_t{a} << 32) | b; }

// Each vertex's faces: a twin edge or a chord is looked up among a few faces, in linear time and
// memory (a hash of every edge cost a large mesh 10 % more time for the few holes it has).
class Fans {
 public:
  explicit Fans(const core::TriangleMesh& mesh) : mesh_(mesh) { core::IncidentFaces(mesh, start_, incident_); }

  std::span<const uint32_t> Of(uint32_t v) const {
    return {incident_.data() + start_[v], incident_.data() + start_[v + 1]};
  }
  // Whether `face` goes from a to b.
  bool Runs(uint32_t face, uint32_t a, uint32_t b) const {
    const Triangle& t = mesh_.faces[face];
    return (t[0] == a && t[1] == b) || (t[1] == a && t[2] == b) || (t[2] == a && t[0] == b);
  }
  bool Has(uint32_t face, uint32_t v) const {
    return std::ranges::find(mesh_.faces[face], v) != mesh_.faces[face].end();
  }
  // The face around `a` that goes from a to b, if exactly one does.
  uint32_t Along(uint32_t a, uint32_t b) const {
    uint32_t found = kNoVertex;
    for (uint32_t g : Of(a)) {
      if (!Runs(g, a, b)) continue;
      if (found != kNoVertex) return kNoVertex;
      found = g;
    }
    return found;
  }
  // Walks the faces around v from the border edge v→y (the hole beyond it) to the border edge
  // x→v that ends the same fan of faces; kNoVertex where the walk does not end within v's faces.
  uint32_t FanEnd(uint32_t v, uint32_t y) const {
    uint32_t face = Along(v, y);
    for (size_t step = 0; face != kNoVertex && step < Of(v).size(); ++step) {
      const Triangle& t = mesh_.faces[face];
      const uint32_t z = t[0] != v && t[0] != y ? t[0] : (t[1] != v && t[1] != y ? t[1] : t[2]);
      const uint32_t twin = Along(v, z);  // The face past the edge z→v.
      if (twin == kNoVertex)
        return std::ranges::none_of(Of(v), [&](uint32_t g) { return Runs(g, v, z); }) ? z : kNoVertex;
      face = twin, y = z;
    }
    return kNoVertex;
  }

 private:
  const core::TriangleMesh& mesh_;
  std::vector<uint32_t> start_, incident_;
};

// The holes' loops, run against the faces around them: border edge a→b gives the filling b→a.
// A vertex where two fans of faces meet (two holes, or one hole's two lobes, touch there) has two
// ways on; each loop takes the one across the gap it arrives in, so the fans are not crossed.
struct HoleLoops {
  absl::flat_hash_map<uint32_t, uint32_t> next;           // Along the loops, at ordinary vertices.
  absl::flat_hash_map<uint64_t, uint32_t> next_at_pinch;  // (previous, pinch vertex) → the next.
  absl::flat_hash_set<uint32_t> pinches;                  // Vertices two fans of faces meet at.
  absl::flat_hash_set<uint32_t> tangled;                  // Vertices no loop may pass.

  HoleLoops(const core::TriangleMesh& mesh, const Fans& fans) {
    absl::flat_hash_map<uint32_t, std::array<uint32_t, 2>> ends;  // A pinch's two border edges x→v.
    for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
      const Triangle& t = mesh.faces[f];
      for (size_t s = 0; s < 3; ++s) {
        const uint32_t a = t[s], b = t[(s + 1) % 3];
        if (a == b) continue;
        int twins = 0, along = 0;
        for (uint32_t g : fans.Of(a)) twins += fans.Runs(g, b, a), along += fans.Runs(g, a, b);
        if (along > 1) tangled.insert(a), tangled.insert(b);
        if (twins > 0) continue;
        const auto [it, fresh] = next.try_emplace(b, a);
        if (fresh) continue;
        if (!ends.try_emplace(b, std::array<uint32_t, 2>{it->second, a}).second)
          tangled.insert(b);  // Three fans or more: which gap is which is not clear.
      }
    }
    for (const auto& [v, pair] : ends) {
      next.erase(v);
      pinches.insert(v);
      if (!tangled.contains(v)) ResolvePinch(mesh, fans, v, pair);
    }
  }

  // The vertex after v on the loop that came to it from `previous`; kNoVertex where none.
  uint32_t After(uint32_t previous, uint32_t v) const {
    if (const auto it = next.find(v); it != next.end()) return it->second;
    const auto it = next_at_pinch.find(Directed(previous, v));
    return it == next_at_pinch.end() ? kNoVertex : it->second;
  }

 private:
  void ResolvePinch(const core::TriangleMesh& mesh, const Fans& fans, uint32_t v, const std::array<uint32_t, 2>& ends) {
    // The loops arrive at v along its border edges v→y, from y.
    std::vector<uint32_t> arrivals;
    for (uint32_t g : fans.Of(v)) {
      const Triangle& t = mesh.faces[g];
      for (size_t s = 0; s < 3; ++s) {
        const uint32_t y = t[(s + 1) % 3];
        if (t[s] == v && std::ranges::none_of(fans.Of(v), [&](uint32_t h) { return fans.Runs(h, y, v); })) {
          arrivals.push_back(y);
        }
      }
    }
    if (arrivals.size() != 2) return tangled.insert(v), void();
    for (uint32_t y : arrivals) {
      // The border edge that ends y's fan is on the far side of it; the loop leaves by the other.
      const uint32_t own = fans.FanEnd(v, y);
      if (own != ends[0] && own != ends[1]) return tangled.insert(v), void();
      next_at_pinch[Directed(y, v)] = own == ends[0] ? ends[1] : ends[0];
    }
  }
};

}  // namespace

double TriangleArea(const Vec3f& a, const Vec3f& b, const Vec3f& c) {
  return 0.5 * static_cast<double>((b - a).cross(c - a).norm());
}

// Barequet & Sharir's dynamic programme: cost[i][j] is the least cost of a fan over loop[i..j]
// closed by the chord (i, j).
bool TriangulateLoop(const std::vector<uint32_t>& loop, const std::vector<Vec3f>& vertices,
                     const std::function<bool(uint32_t, uint32_t)>& is_edge,
                     const std::function<double(const Vec3f&, const Vec3f&, const Vec3f&)>& cost_of,
                     std::vector<Triangle>& out) {
  const size_t n = loop.size();
  std::vector<bool> again(n, false);
  for (size_t i = 1; i < n; ++i)
    again[i] = std::find(loop.begin(), loop.begin() + static_cast<std::ptrdiff_t>(i), loop[i]) !=
               loop.begin() + static_cast<std::ptrdiff_t>(i);
  constexpr double kNone = std::numeric_limits<double>::infinity();
  std::vector<double> cost(n * n, kNone);
  std::vector<uint32_t> split(n * n, 0);
  auto at = [n](size_t i, size_t j) { return i * n + j; };
  for (size_t i = 0; i + 1 < n; ++i) cost[at(i, i + 1)] = 0;
  for (size_t span = 2; span < n; ++span) {
    for (size_t i = 0; i + span < n; ++i) {
      const size_t j = i + span;
      // (0, n−1) is a border edge; every other chord must be new.
      if (!(i == 0 && j == n - 1) && (again[i] || again[j] || is_edge(loop[i], loop[j]))) continue;
      const Vec3f &a = vertices[loop[i]], &c = vertices[loop[j]];
      for (size_t k = i + 1; k < j; ++k) {
        const double sides = cost[at(i, k)] + cost[at(k, j)];
        if (sides == kNone) continue;
        const double total = sides + cost_of(a, vertices[loop[k]], c);
        if (total < cost[at(i, j)]) cost[at(i, j)] = total, split[at(i, j)] = static_cast<uint32_t>(k);
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

struct HoleBorders::State {
  const core::TriangleMesh& mesh;
  const size_t vertices;  // The mesh's when made; later ones have no fans.
  Fans fans;
  HoleLoops loops;
  explicit State(const core::TriangleMesh& m) : mesh(m), vertices(m.vertices.size()), fans(m), loops(m, fans) {
    // Border vertices at one position: welded, their borders may close each other.
    absl::flat_hash_map<std::array<float, 3>, uint32_t> at;
    auto weld = [&](uint32_t v) {
      const Vec3f& p = mesh.vertices[v];
      const auto [it, fresh] = at.try_emplace(std::array<float, 3>{p.x(), p.y(), p.z()}, v);
      if (!fresh) loops.tangled.insert(v), loops.tangled.insert(it->second);
    };
    for (const auto& [v, unused] : loops.next) weld(v);
    for (uint32_t v : loops.pinches) weld(v);
  }
};

HoleBorders::HoleBorders(const core::TriangleMesh& mesh) : state_(std::make_unique<State>(mesh)) {}
HoleBorders::~HoleBorders() = default;

bool HoleBorders::IsEdge(uint32_t a, uint32_t b) const {
  const Fans& fans = state_->fans;
  if (a >= state_->vertices || b >= state_->vertices) return false;
  return std::ranges::any_of(fans.Of(a), [&](uint32_t g) { return fans.Has(g, b); });
}

void HoleBorders::FacesAround(uint32_t v, std::vector<uint32_t>& out) const {
  out.clear();
  if (v >= state_->vertices) return;
  for (uint32_t g : state_->fans.Of(v)) out.push_back(g);
}

std::vector<std::vector<uint32_t>> HoleBorders::Loops(size_t max_edges) {
  const HoleLoops& loops = state_->loops;
  std::vector<std::vector<uint32_t>> found;
  absl::flat_hash_set<uint32_t> visited;  // Ordinary vertices; a pinch vertex is on two loops.
  std::vector<uint32_t> loop;
  // Walked from the lowest vertex up, not in the hash map's order (seeded per process): the same
  // mesh gives the same loops, starts and so the same filled mesh on every run.
  std::vector<uint32_t> starts;
  starts.reserve(loops.next.size());
  for (const auto& [v, unused] : loops.next) starts.push_back(v);
  std::ranges::sort(starts);
  for (uint32_t first : starts) {
    if (visited.contains(first)) continue;
    loop.clear();
    bool closed = false, usable = true;
    for (uint32_t v = first, previous = kNoVertex; v != kNoVertex;) {
      // A hole whose border touches itself at a pinch passes it twice (its fill is one disk).
      const bool pinch = loops.pinches.contains(v);
      if (pinch ? std::ranges::count(loop, v) == 2 : !visited.insert(v).second) {
        closed = v == first;
        break;
      }
      loop.push_back(v);
      usable &= !loops.tangled.contains(v);
      // Too long to close: the rest of it is walked from its own vertices, a stretch at a time.
      if (max_edges > 0 && loop.size() > max_edges) break;
      const uint32_t after = loops.After(previous, v);
      previous = v, v = after;
    }
    if (closed && !usable && max_edges == 0) ++tangled_loops_;
    if (!closed || !usable || loop.size() < 3) continue;
    // Three border edges around a face of their own: a lone triangle, not a hole.
    if (loop.size() == 3 && std::ranges::any_of(state_->fans.Of(loop[0]), [&](uint32_t g) {
          return state_->fans.Has(g, loop[1]) && state_->fans.Has(g, loop[2]);
        })) {
      continue;
    }
    found.push_back(loop);
  }
  return found;
}

int64_t FillSmallHoles(core::TriangleMesh& mesh, int max_edges, const std::function<bool(const Vec3f&)>& keep_open) {
  max_edges = std::min(max_edges, kMaxHoleEdges);
  if (max_edges < 3 || mesh.faces.empty()) return 0;
  // A closed mesh (the common case) pays one pass over its faces.
  uint64_t unmatched = 0;
  for (const Triangle& t : mesh.faces) unmatched += core::UnmatchedEdgeSum(t);
  if (unmatched == 0) return 0;
  HoleBorders borders(mesh);
  const std::vector<std::vector<uint32_t>> loops = borders.Loops(static_cast<size_t>(max_edges));
  absl::flat_hash_set<uint64_t> added;  // Edges of the fillings so far.
  auto is_edge = [&](uint32_t a, uint32_t b) { return borders.IsEdge(a, b) || added.contains(Undirected(a, b)); };
  int64_t filled = 0;
  std::vector<Triangle> patch;
  for (const std::vector<uint32_t>& loop : loops) {
    if (keep_open && std::ranges::any_of(loop, [&](uint32_t v) { return keep_open(mesh.vertices[v]); })) continue;
    patch.clear();
    if (!TriangulateLoop(loop, mesh.vertices, is_edge, TriangleArea, patch)) continue;
    for (const Triangle& t : patch) {
      for (size_t s = 0; s < 3; ++s) added.insert(Undirected(t[s], t[(s + 1) % 3]));
      mesh.faces.push_back(t);
    }
    ++filled;
  }
  return filled;
}

}  // namespace lsqsurf::extract::internal
