#include "worker/core/isosurface.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"

namespace lsqsurf::core {
namespace {

// Grid coordinates are packed 20 bits per axis (biased), so a vertex key fits in 60 bits and
// an edge key (vertex key × 8 + direction) in 63.
constexpr int kBits = 20;
constexpr int64_t kBias = int64_t{1} << (kBits - 1);
constexpr int64_t kLimit = kBias - 2;

using Key = uint64_t;

Key Pack(int64_t x, int64_t y, int64_t z) {
  return (static_cast<uint64_t>(x + kBias) << (2 * kBits)) |
         (static_cast<uint64_t>(y + kBias) << kBits) | static_cast<uint64_t>(z + kBias);
}

std::array<int64_t, 3> Unpack(Key k) {
  const uint64_t mask = (uint64_t{1} << kBits) - 1;
  return {static_cast<int64_t>((k >> (2 * kBits)) & mask) - kBias,
          static_cast<int64_t>((k >> kBits) & mask) - kBias, static_cast<int64_t>(k & mask) - kBias};
}

// Corner c of a cube has offset (c & 1, c >> 1 & 1, c >> 2 & 1).
Key CornerKey(Key cell, int c) {
  const auto [x, y, z] = Unpack(cell);
  return Pack(x + (c & 1), y + ((c >> 1) & 1), z + ((c >> 2) & 1));
}

// The 6 Kuhn tetrahedra of a cube: chains 0 ⊂ 1<<a ⊂ 1<<a|1<<b ⊂ 7 over the axis orders.
constexpr std::array<std::array<int, 4>, 6> kTets = {{{0, 1, 3, 7},
                                                      {0, 1, 5, 7},
                                                      {0, 2, 3, 7},
                                                      {0, 2, 6, 7},
                                                      {0, 4, 5, 7},
                                                      {0, 4, 6, 7}}};

// The 4 corners of each face, for the six directions −x, +x, −y, +y, −z, +z.
std::array<int, 4> FaceCorners(int face) {
  const int axis = face / 2, bit = 1 << axis, side = face % 2;
  std::array<int, 4> out{};
  int n = 0;
  for (int c = 0; c < 8; ++c) {
    if (((c & bit) != 0) == (side == 1)) out[static_cast<size_t>(n++)] = c;
  }
  return out;
}

Vec3d UnitCorner(int c) { return Vec3d(c & 1, (c >> 1) & 1, (c >> 2) & 1); }

// An output vertex lives on the tetrahedron edge from corner `lo` to corner `hi` of a cube
// (`lo` ⊂ `hi` bitwise, as on every Kuhn edge); the key names the grid edge independently of
// which cube it was seen from.
Key EdgeKey(Key cell, int lo, int hi) { return CornerKey(cell, lo) * 8 + static_cast<Key>(hi & ~lo); }

struct Crossing {
  Key inside_vertex;   // Grid vertex with F < 0.
  Key outside_vertex;  // Grid vertex with F >= 0.
  double inside_value;
  double outside_value;
};

// Marks as trusted again every edge-connected cluster of untrusted triangles with at most
// `max_size` members: such pinholes lie on the real surface where the field's confidence dips
// for a moment (a gap in random sampling), and dropping them would open the surface. Large
// clusters (holes in the data, ghost sheets) stay untrusted. Returns the triangles restored.
int64_t RestoreSmallPatches(const std::vector<Triangle>& faces, std::vector<char>& trusted,
                            int max_size) {
  if (max_size <= 0) return 0;
  struct Side {
    uint32_t lo, hi, face;
  };
  std::vector<Side> sides;
  for (uint32_t f = 0; f < faces.size(); ++f) {
    if (trusted[f]) continue;
    for (int i = 0; i < 3; ++i) {
      const uint32_t a = faces[f][static_cast<size_t>(i)], b = faces[f][static_cast<size_t>((i + 1) % 3)];
      sides.push_back({std::min(a, b), std::max(a, b), f});
    }
  }
  std::sort(sides.begin(), sides.end(), [](const Side& x, const Side& y) {
    return x.lo != y.lo ? x.lo < y.lo : x.hi < y.hi;
  });
  absl::flat_hash_map<uint32_t, uint32_t> parent;
  auto find = [&](uint32_t x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  };
  for (const Side& s : sides) parent.try_emplace(s.face, s.face);
  for (size_t i = 1; i < sides.size(); ++i) {
    if (sides[i].lo == sides[i - 1].lo && sides[i].hi == sides[i - 1].hi) {
      parent[find(sides[i].face)] = find(sides[i - 1].face);
    }
  }
  absl::flat_hash_map<uint32_t, int> size;
  for (auto& [face, p] : parent) ++size[find(face)];
  int64_t restored = 0;
  for (auto& [face, p] : parent) {
    if (size[find(face)] <= max_size) {
      trusted[face] = 1;
      ++restored;
    }
  }
  return restored;
}

}  // namespace

absl::Status Validate(const IsosurfaceParams& params) {
  if (!(params.cell_size > 0.0) || !std::isfinite(params.cell_size)) {
    return absl::InvalidArgumentError("cell_size must be a positive number");
  }
  if (params.refine_steps < 0 || params.refine_steps > 20) {
    return absl::InvalidArgumentError("refine_steps must be between 0 and 20");
  }
  if (params.max_cells <= 0) return absl::InvalidArgumentError("max_cells must be positive");
  return absl::OkStatus();
}

absl::StatusOr<IsosurfaceResult> ExtractIsosurface(const ImplicitFunction& field,
                                                   std::span<const Vec3f> seeds,
                                                   const IsosurfaceParams& params,
                                                   JobContext& ctx) {
  if (absl::Status s = Validate(params); !s.ok()) return s;
  if (seeds.empty()) return absl::InvalidArgumentError("isosurface extraction needs seed points");
  const Box3 box = BoundingBox(seeds);
  const double h = params.cell_size;
  if ((box.sizes() / h).maxCoeff() > static_cast<double>(kLimit)) {
    return absl::InvalidArgumentError(
        "cell_size is too small for the extent of the data (more than 500,000 cells per axis)");
  }
  // Half a cell of offset keeps samples on regular grids off the grid vertices.
  const Vec3d origin = box.min() - Vec3d::Constant(0.5 * h);
  auto vertex_position = [&](Key k) {
    const auto [x, y, z] = Unpack(k);
    return Vec3d(origin + h * Vec3d(static_cast<double>(x), static_cast<double>(y),
                                    static_cast<double>(z)));
  };

  IsosurfaceResult result;
  IsosurfaceStats& stats = result.stats;
  SubContext track_ctx(ctx, "tracking surface", 0.0, 0.75);

  absl::flat_hash_set<Key> visited;
  std::vector<Key> frontier;
  for (const Vec3f& p : seeds) {
    const Vec3d g = (p.cast<double>() - origin) / h;
    const Key k = Pack(static_cast<int64_t>(std::floor(g.x())), static_cast<int64_t>(std::floor(g.y())),
                       static_cast<int64_t>(std::floor(g.z())));
    if (visited.insert(k).second) frontier.push_back(k);
  }
  const double seed_cells = static_cast<double>(frontier.size());

  absl::flat_hash_map<Key, FieldValue> values;
  std::vector<Key> surface_cells;
  std::vector<Key> pending;
  std::vector<Vec3d> pending_positions;
  std::vector<FieldValue> pending_values;
  while (!frontier.empty()) {
    stats.cells_visited += static_cast<int64_t>(frontier.size());
    if (stats.cells_visited > params.max_cells) {
      return absl::ResourceExhaustedError(
          "the surface needs more than " + std::to_string(params.max_cells) +
          " grid cells; raise cell_size or the cell limit");
    }
    pending.clear();
    for (Key cell : frontier) {
      for (int c = 0; c < 8; ++c) {
        const Key v = CornerKey(cell, c);
        if (values.try_emplace(v).second) pending.push_back(v);
      }
    }
    pending_positions.resize(pending.size());
    pending_values.resize(pending.size());
    for (size_t i = 0; i < pending.size(); ++i) pending_positions[i] = vertex_position(pending[i]);
    LSQSURF_RETURN_IF_ERROR(field.ValueBatch(pending_positions, pending_values, &ctx));
    for (size_t i = 0; i < pending.size(); ++i) values[pending[i]] = pending_values[i];
    stats.field_evaluations += static_cast<int64_t>(pending.size());

    std::vector<Key> next;
    for (Key cell : frontier) {
      std::array<FieldValue, 8> corner;
      for (int c = 0; c < 8; ++c) corner[static_cast<size_t>(c)] = values.at(CornerKey(cell, c));
      bool crossed = false;
      for (int face = 0; face < 6; ++face) {
        bool neg = false, pos = false;
        for (int c : FaceCorners(face)) {
          const FieldValue& fv = corner[static_cast<size_t>(c)];
          if (std::isnan(fv.value)) continue;
          (fv.value < 0 ? neg : pos) = true;
        }
        if (!(neg && pos)) continue;
        crossed = true;
        auto [x, y, z] = Unpack(cell);
        const int axis = face / 2, step = face % 2 == 1 ? 1 : -1;
        (axis == 0 ? x : axis == 1 ? y : z) += step;
        if (std::abs(x) > kLimit || std::abs(y) > kLimit || std::abs(z) > kLimit) continue;
        const Key neighbor = Pack(x, y, z);
        if (visited.insert(neighbor).second) next.push_back(neighbor);
      }
      if (crossed) surface_cells.push_back(cell);
    }
    frontier = std::move(next);
    track_ctx.Report(1.0 - std::min(1.0, static_cast<double>(frontier.size()) /
                                             std::max(1.0, seed_cells)));
  }
  stats.surface_cells = static_cast<int64_t>(surface_cells.size());
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());

  // Marching tetrahedra: each polygon is a list of edge indices, already oriented so that its
  // normal points from F < 0 to F >= 0 (decided on the unit cube, where no tetrahedron is flat).
  SubContext emit_ctx(ctx, "extracting triangles", 0.75, 1.0);
  absl::flat_hash_map<Key, uint32_t> edge_index;
  std::vector<Crossing> crossings;
  std::vector<std::array<uint32_t, 4>> polygons;  // [3] == UINT32_MAX for a triangle.
  for (Key cell : surface_cells) {
    std::array<FieldValue, 8> corner;
    for (int c = 0; c < 8; ++c) corner[static_cast<size_t>(c)] = values.at(CornerKey(cell, c));
    for (const auto& tet : kTets) {
      std::array<int, 4> inside{}, outside{};
      int n_in = 0, n_out = 0;
      bool defined = true;
      for (int c : tet) {
        const FieldValue& fv = corner[static_cast<size_t>(c)];
        defined &= !std::isnan(fv.value);
        if (fv.value < 0) inside[static_cast<size_t>(n_in++)] = c;
        else outside[static_cast<size_t>(n_out++)] = c;
      }
      if (!defined || n_in == 0 || n_out == 0) continue;
      auto edge = [&](int a, int b) {  // a inside, b outside
        const int lo = std::min(a, b), hi = std::max(a, b);
        const Key key = EdgeKey(cell, lo, hi);
        auto [it, inserted] = edge_index.try_emplace(key, static_cast<uint32_t>(crossings.size()));
        if (inserted) {
          crossings.push_back({CornerKey(cell, a), CornerKey(cell, b),
                               corner[static_cast<size_t>(a)].value,
                               corner[static_cast<size_t>(b)].value});
        }
        return it->second;
      };
      auto mid = [](int a, int b) { return Vec3d(0.5 * (UnitCorner(a) + UnitCorner(b))); };
      Vec3d in_c = Vec3d::Zero(), out_c = Vec3d::Zero();
      for (int i = 0; i < n_in; ++i) in_c += UnitCorner(inside[static_cast<size_t>(i)]) / n_in;
      for (int i = 0; i < n_out; ++i) out_c += UnitCorner(outside[static_cast<size_t>(i)]) / n_out;
      const Vec3d outward = out_c - in_c;
      std::array<std::pair<int, int>, 4> ring{};
      int ring_size = 0;
      if (n_in == 1) {
        for (int i = 0; i < 3; ++i) ring[static_cast<size_t>(ring_size++)] = {inside[0], outside[static_cast<size_t>(i)]};
      } else if (n_out == 1) {
        for (int i = 0; i < 3; ++i) ring[static_cast<size_t>(ring_size++)] = {inside[static_cast<size_t>(i)], outside[0]};
      } else {  // Two and two: the crossings form the cycle ac, ad, bd, bc.
        const int a = inside[0], b = inside[1], c = outside[0], d = outside[1];
        ring = {{{a, c}, {a, d}, {b, d}, {b, c}}};
        ring_size = 4;
      }
      const Vec3d p0 = mid(ring[0].first, ring[0].second);
      const Vec3d p1 = mid(ring[1].first, ring[1].second);
      const Vec3d p2 = mid(ring[2].first, ring[2].second);
      const bool flip = (p1 - p0).cross(p2 - p0).dot(outward) < 0;
      std::array<uint32_t, 4> poly{UINT32_MAX, UINT32_MAX, UINT32_MAX, UINT32_MAX};
      for (int i = 0; i < ring_size; ++i) {
        const int j = flip ? ring_size - 1 - i : i;
        poly[static_cast<size_t>(i)] = edge(ring[static_cast<size_t>(j)].first, ring[static_cast<size_t>(j)].second);
      }
      polygons.push_back(poly);
    }
  }
  values.clear();
  values.rehash(0);

  // Root refinement on the true F along each crossing edge (Illinois variant of regula falsi:
  // superlinear, and it never leaves the bracket).
  TriangleMesh& mesh = result.mesh;
  mesh.vertices.resize(crossings.size());
  if (params.vertex_normals) mesh.normals.resize(crossings.size());
  std::vector<char> valid(crossings.size(), 0);
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      crossings.size(), 256,
      [&](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) {
          const Crossing& c = crossings[i];
          const Vec3d a = vertex_position(c.inside_vertex), b = vertex_position(c.outside_vertex);
          double ta = 0.0, tb = 1.0, fa = c.inside_value, fb = c.outside_value;
          double t = fa / (fa - fb);
          int side = 0;
          for (int step = 0; step < params.refine_steps; ++step) {
            const FieldValue fv = field.Value(a + t * (b - a));
            if (std::isnan(fv.value) || fv.value == 0.0) break;
            if (fv.value < 0) {
              ta = t, fa = fv.value;
              if (side == -1) fb *= 0.5;
              side = -1;
            } else {
              tb = t, fb = fv.value;
              if (side == 1) fa *= 0.5;
              side = 1;
            }
            t = ta - fa * (tb - ta) / (fb - fa);
          }
          // Keep vertices strictly inside their edge: coincident vertices would make
          // zero-area triangles that some decoders drop.
          t = std::clamp(t, 1e-4, 1.0 - 1e-4);
          const Vec3d x = a + t * (b - a);
          mesh.vertices[i] = x.cast<float>();
          // A root where F is not trustworthy (e.g. an iaMLS ghost sheet, or a sign-only
          // extension of F across a hole in the data) is no surface: drop what uses it.
          const FieldGradient g = field.ValueAndGradient(x);
          valid[i] = g.defined;
          if (params.vertex_normals) {
            const double len = g.gradient.norm();
            mesh.normals[i] = len > 0 ? Vec3f((g.gradient / len).cast<float>())
                                      : Vec3f((b - a).normalized().cast<float>());
          }
        }
      },
      &ctx, [&](double f) { emit_ctx.Report(0.9 * f); }));

  mesh.faces.reserve(polygons.size() * 3 / 2);
  std::vector<char> face_trusted;
  face_trusted.reserve(polygons.size() * 3 / 2);
  for (const auto& p : polygons) {
    const bool trusted = valid[p[0]] && valid[p[1]] && valid[p[2]] &&
                         (p[3] == UINT32_MAX || valid[p[3]]);
    const size_t before = mesh.faces.size();
    if (p[3] == UINT32_MAX) {
      mesh.faces.push_back({p[0], p[1], p[2]});
    } else {
      // Split the quad along its shorter diagonal for better-shaped triangles.
      const float d02 = (mesh.vertices[p[0]] - mesh.vertices[p[2]]).squaredNorm();
      const float d13 = (mesh.vertices[p[1]] - mesh.vertices[p[3]]).squaredNorm();
      if (d02 <= d13) {
        mesh.faces.push_back({p[0], p[1], p[2]});
        mesh.faces.push_back({p[0], p[2], p[3]});
      } else {
        mesh.faces.push_back({p[0], p[1], p[3]});
        mesh.faces.push_back({p[1], p[2], p[3]});
      }
    }
    face_trusted.resize(mesh.faces.size(), trusted);
    if (!trusted) stats.rejected_polygons += static_cast<int64_t>(mesh.faces.size() - before);
  }
  stats.restored_triangles = RestoreSmallPatches(mesh.faces, face_trusted, params.max_patch_triangles);
  stats.rejected_polygons -= stats.restored_triangles;
  {
    size_t kept_faces = 0;
    for (size_t f = 0; f < mesh.faces.size(); ++f) {
      if (face_trusted[f]) mesh.faces[kept_faces++] = mesh.faces[f];
    }
    mesh.faces.resize(kept_faces);
  }

  // Drop the vertices that only rejected polygons used.
  std::vector<uint32_t> remap(mesh.vertices.size(), UINT32_MAX);
  std::vector<Vec3f> kept_vertices, kept_normals;
  kept_vertices.reserve(mesh.vertices.size());
  for (auto& f : mesh.faces) {
    for (uint32_t& v : f) {
      if (remap[v] == UINT32_MAX) {
        remap[v] = static_cast<uint32_t>(kept_vertices.size());
        kept_vertices.push_back(mesh.vertices[v]);
        if (params.vertex_normals) kept_normals.push_back(mesh.normals[v]);
      }
      v = remap[v];
    }
  }
  mesh.vertices = std::move(kept_vertices);
  mesh.normals = std::move(kept_normals);
  const auto kept = mesh.vertices.size();
  stats.crossings = static_cast<int64_t>(kept);
  emit_ctx.Report(1.0);
  return result;
}

}  // namespace lsqsurf::core
