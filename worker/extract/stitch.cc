#include "worker/extract/stitch.h"

#include <algorithm>
#include <string>
#include <utility>

#include "absl/container/flat_hash_map.h"
#include "worker/core/status.h"

namespace lsqsurf::extract {
namespace {

// A directed edge as one key.
uint64_t Directed(uint32_t from, uint32_t to) { return (uint64_t{from} << 32) | to; }

absl::Status Refuse(std::string_view why) {
  return absl::FailedPreconditionError(std::string("the patch does not join the kept mesh: ") + std::string(why));
}

// A kept border path to put into the patch face along a seam edge.
struct Insertion {
  uint32_t face;                 // Patch face with the edge from → to.
  uint32_t from, to;             // Patch vertices.
  std::vector<uint32_t> inside;  // Kept vertices between them, in the order from → to.
};

// The kept mesh's border around the removed faces: next[x] holds y for every edge x → y of a
// remaining face whose twin y → x was removed (two where the border touches itself at x).
using BorderMap = absl::flat_hash_map<uint32_t, std::vector<uint32_t>>;
BorderMap HoleBorder(const TriangleMesh& kept, const std::vector<char>& removed) {
  std::vector<char> touched(kept.vertices.size(), 0);
  absl::flat_hash_set<uint64_t> removed_edges;
  for (size_t f = 0; f < kept.faces.size(); ++f) {
    if (!removed[f]) continue;
    const Triangle& t = kept.faces[f];
    for (size_t i = 0; i < 3; ++i) {
      removed_edges.insert(Directed(t[i], t[(i + 1) % 3]));
      touched[t[i]] = 1;
    }
  }
  BorderMap next;
  for (size_t f = 0; f < kept.faces.size(); ++f) {
    const Triangle& t = kept.faces[f];
    if (removed[f] || !(touched[t[0]] || touched[t[1]] || touched[t[2]])) continue;
    for (size_t i = 0; i < 3; ++i) {
      const uint32_t x = t[i], y = t[(i + 1) % 3];
      if (removed_edges.contains(Directed(y, x))) next[x].push_back(y);
    }
  }
  return next;
}

// Kept crease vertices on seam edges split the patch face along the edge into a fan; in face
// order, not the edge map's (seeded per table), so the fans' faces are numbered alike each run.
// The new patch vertices are the kept ones (`kept_vertex`, `fixed` grow with them).
absl::Status SplitSeamFaces(const TriangleMesh& kept, bool normals, std::vector<Insertion> insertions,
                            IsosurfaceResult& patch, std::vector<uint32_t>& kept_vertex, std::vector<char>& fixed) {
  TriangleMesh& pm = patch.mesh;
  std::ranges::sort(insertions, {}, &Insertion::face);
  absl::flat_hash_set<uint32_t> split_faces;
  for (const Insertion& ins : insertions) {
    if (!split_faces.insert(ins.face).second) return Refuse("a patch face with two split seam edges");
    const Triangle t = pm.faces[ins.face];
    const uint32_t apex = t[0] != ins.from && t[0] != ins.to ? t[0] : t[1] != ins.from && t[1] != ins.to ? t[1] : t[2];
    const uint64_t cell = patch.trace.face_cells[ins.face];
    uint32_t previous = ins.from;
    bool first = true;
    for (const uint32_t k : ins.inside) {
      const auto v = static_cast<uint32_t>(pm.vertices.size());
      pm.vertices.push_back(kept.vertices[k]);
      if (!pm.normals.empty()) pm.normals.push_back(normals ? kept.normals[k] : pm.normals[ins.from]);
      patch.trace.vertex_edges.push_back(0);
      kept_vertex.push_back(k);
      fixed.push_back(1);
      const Triangle piece{previous, v, apex};
      if (first) {
        pm.faces[ins.face] = piece;
        first = false;
      } else {
        pm.faces.push_back(piece);
        patch.trace.face_cells.push_back(cell);
      }
      previous = v;
    }
    pm.faces.push_back({previous, ins.to, apex});
    patch.trace.face_cells.push_back(cell);
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<PatchJoin> PatchJoin::Prepare(const TriangleMesh& kept, const SurfaceTrace& kept_trace,
                                             const absl::flat_hash_set<uint64_t>& cells, IsosurfaceResult& patch) {
  TriangleMesh& pm = patch.mesh;
  if (kept_trace.face_cells.size() != kept.faces.size() || kept_trace.vertex_edges.size() != kept.vertices.size() ||
      patch.trace.face_cells.size() != pm.faces.size() || patch.trace.vertex_edges.size() != pm.vertices.size()) {
    return Refuse("a mesh without its trace");
  }
  PatchJoin join;
  join.removed_.assign(kept.faces.size(), 0);
  for (size_t f = 0; f < kept.faces.size(); ++f) {
    if (cells.contains(kept_trace.face_cells[f])) {
      join.removed_[f] = 1;
      ++join.removed_faces_;
    }
  }
  BorderMap next = HoleBorder(kept, join.removed_);
  int64_t hole_edges = 0;
  // The hole's border vertices by the lattice edge they were marched on.
  absl::flat_hash_map<uint64_t, uint32_t> by_edge;
  for (const auto& [from, ends] : next) {
    hole_edges += static_cast<int64_t>(ends.size());
    // The ends too: where the kept mesh had a border of its own, a hole edge can end there.
    for (const uint32_t v : ends) {
      for (const uint32_t w : {from, v}) {
        const uint64_t name = kept_trace.vertex_edges[w];
        if (name == 0) continue;
        if (const auto [it, fresh] = by_edge.emplace(name, w); !fresh && it->second != w) {
          return Refuse("two border vertices on one lattice edge");
        }
      }
    }
  }
  absl::flat_hash_map<uint64_t, uint32_t> patch_edges;  // Directed edge → its face.
  for (uint32_t f = 0; f < pm.faces.size(); ++f) {
    for (size_t i = 0; i < 3; ++i) {
      if (!patch_edges.emplace(Directed(pm.faces[f][i], pm.faces[f][(i + 1) % 3]), f).second) {
        return Refuse("the patch is not edge-manifold");
      }
    }
  }
  join.kept_vertex_.assign(pm.vertices.size(), UINT32_MAX);
  for (size_t v = 0; v < pm.vertices.size(); ++v) {
    if (const auto it = by_edge.find(patch.trace.vertex_edges[v]); it != by_edge.end())
      join.kept_vertex_[v] = it->second;
  }
  // Each patch border edge a → b on the seam faces the kept border path b → … → a.
  constexpr int kMostInserted = 8;
  std::vector<Insertion> insertions;
  for (const auto& [edge, face] : patch_edges) {
    const auto a = static_cast<uint32_t>(edge >> 32), b = static_cast<uint32_t>(edge);
    if (patch_edges.contains(Directed(b, a))) continue;
    const uint32_t ka = join.kept_vertex_[a], kb = join.kept_vertex_[b];
    if (ka == UINT32_MAX && kb == UINT32_MAX) continue;  // The patch's own border (F undefined there).
    if (ka == UINT32_MAX || kb == UINT32_MAX) return Refuse("a patch border meets the seam at one end");
    std::vector<uint32_t> path;
    uint32_t v = kb;
    for (int step = 0; step <= kMostInserted && v != ka; ++step) {
      const auto it = next.find(v);
      if (it == next.end() || it->second.empty()) return Refuse("a seam edge has no kept counterpart");
      // Where the border touches itself, the end that continues towards `ka`: `ka` itself, or a
      // crease vertex (never two of those).
      std::vector<uint32_t>& ends = it->second;
      auto end = std::find(ends.begin(), ends.end(), ka);
      if (end == ends.end()) {
        end = std::find_if(ends.begin(), ends.end(), [&](uint32_t e) { return kept_trace.vertex_edges[e] == 0; });
      }
      if (end == ends.end()) return Refuse("the seam's vertices differ");
      v = *end;
      ends.erase(end);  // Each kept border edge is matched once.
      if (v != ka) {
        if (kept_trace.vertex_edges[v] != 0) return Refuse("the seam's vertices differ");
        path.push_back(v);
      }
    }
    if (v != ka) return Refuse("a kept seam edge is split too often");
    join.seam_edges_ += 1 + static_cast<int64_t>(path.size());
    if (!path.empty()) insertions.push_back({face, a, b, {path.rbegin(), path.rend()}});
  }
  if (join.seam_edges_ != hole_edges) return Refuse("part of the hole's border stays open");
  // The seam takes the kept positions and normals.
  const bool normals = !pm.normals.empty() && !kept.normals.empty();
  join.fixed_.assign(pm.vertices.size(), 0);
  for (size_t v = 0; v < pm.vertices.size(); ++v) {
    const uint32_t k = join.kept_vertex_[v];
    if (k == UINT32_MAX) continue;
    join.fixed_[v] = 1;
    pm.vertices[v] = kept.vertices[k];
    if (normals) pm.normals[v] = kept.normals[k];
  }
  LSQSURF_RETURN_IF_ERROR(SplitSeamFaces(kept, normals, std::move(insertions), patch, join.kept_vertex_, join.fixed_));
  return join;
}

TriangleMesh PatchJoin::Merge(TriangleMesh kept, SurfaceTrace kept_trace, const IsosurfaceResult& patch,
                              SurfaceTrace& trace) const {
  const TriangleMesh& pm = patch.mesh;
  TriangleMesh out = std::move(kept);
  trace = std::move(kept_trace);
  const bool normals = !out.normals.empty() && !pm.normals.empty();
  if (!normals) out.normals.clear();
  // The kept vertices that remaining faces use keep their order, moved down in place.
  std::vector<char> used(out.vertices.size(), 0);
  for (size_t f = 0; f < out.faces.size(); ++f) {
    if (!removed_[f]) used[out.faces[f][0]] = used[out.faces[f][1]] = used[out.faces[f][2]] = 1;
  }
  std::vector<uint32_t> from_kept(out.vertices.size(), UINT32_MAX);
  uint32_t count = 0;
  for (size_t v = 0; v < out.vertices.size(); ++v) {
    if (!used[v]) continue;
    out.vertices[count] = out.vertices[v];
    if (normals) out.normals[count] = out.normals[v];
    trace.vertex_edges[count] = trace.vertex_edges[v];
    for (core::ScalarAttribute& a : out.vertex_attributes) a.values[count] = a.values[v];
    from_kept[v] = count++;
  }
  out.vertices.resize(count);
  if (normals) out.normals.resize(count);
  trace.vertex_edges.resize(count);
  for (core::ScalarAttribute& a : out.vertex_attributes) a.values.resize(count);
  size_t faces = 0;
  for (size_t f = 0; f < out.faces.size(); ++f) {
    if (removed_[f]) continue;
    for (uint32_t k = 0; k < 3; ++k) out.faces[faces][k] = from_kept[out.faces[f][k]];
    trace.face_cells[faces++] = trace.face_cells[f];
  }
  out.faces.resize(faces);
  trace.face_cells.resize(faces);
  // The patch's vertices: the seam's are kept ones, the rest are appended.
  std::vector<const core::ScalarAttribute*> patch_attributes;
  for (const core::ScalarAttribute& a : out.vertex_attributes) {
    const core::ScalarAttribute* match = nullptr;
    for (const core::ScalarAttribute& b : pm.vertex_attributes) {
      if (b.name == a.name) match = &b;
    }
    patch_attributes.push_back(match);
  }
  std::vector<uint32_t> from_patch(pm.vertices.size(), UINT32_MAX);
  for (size_t v = 0; v < pm.vertices.size(); ++v) {
    const uint32_t k = v < kept_vertex_.size() ? kept_vertex_[v] : UINT32_MAX;
    if (k != UINT32_MAX && from_kept[k] != UINT32_MAX) {
      from_patch[v] = from_kept[k];
      continue;
    }
    from_patch[v] = static_cast<uint32_t>(out.vertices.size());
    out.vertices.push_back(pm.vertices[v]);
    if (normals) out.normals.push_back(pm.normals[v]);
    trace.vertex_edges.push_back(patch.trace.vertex_edges[v]);
    for (size_t i = 0; i < out.vertex_attributes.size(); ++i) {
      out.vertex_attributes[i].values.push_back(patch_attributes[i] ? patch_attributes[i]->values[v] : 0.0f);
    }
  }
  for (size_t f = 0; f < pm.faces.size(); ++f) {
    Triangle t = pm.faces[f];
    for (uint32_t& v : t) v = from_patch[v];
    out.faces.push_back(t);
    trace.face_cells.push_back(patch.trace.face_cells[f]);
  }
  return out;
}

}  // namespace lsqsurf::extract
