// Volume meshes as exporters write them (volume_mesh.h, RepairVolumeMesh): quadratic cells,
// either vertex order, duplicate and unused points, slivers, and holes in the data.
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numeric>
#include <span>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/core/volume_mesh.h"

namespace lsqsurf::core {
namespace {

constexpr uint8_t kQuadraticTetra = 24, kQuadraticHexahedron = 25, kQuadraticWedge = 26, kQuadraticPyramid = 27;

// A quadratic tetrahedron as eight linear ones over its corners and edge midpoints (VTK's node
// order: corners 0-3, then the midpoints of 01, 12, 20, 03, 13, 23), so that every node's data
// stays in the field. The inner octahedron is cut along the diagonal 4-9; orientation is fixed
// afterwards with every other cell's.
constexpr std::array<std::array<uint8_t, 4>, 8> kQuadraticTetraSplit = {
    {{0, 4, 6, 7}, {4, 1, 5, 8}, {6, 5, 2, 9}, {7, 8, 9, 3}, {4, 9, 5, 8}, {4, 9, 8, 7}, {4, 9, 7, 6}, {4, 9, 6, 5}}};

// The linear cell a quadratic one stands for on its corners (the other quadratic types carry
// no node inside, so there is no finer split that keeps every node without new points).
CellType LinearOf(uint8_t quadratic) {
  switch (quadratic) {
    case kQuadraticHexahedron: return CellType::kHexahedron;
    case kQuadraticWedge: return CellType::kWedge;
    default: return CellType::kPyramid;
  }
}

// Replaces quadratic cells by linear ones; `source` maps each new cell to the cell it came from.
int64_t Linearise(VolumeMesh& mesh, std::vector<uint32_t>& source) {
  const bool any = std::any_of(mesh.cell_types.begin(), mesh.cell_types.end(), [](uint8_t t) { return t >= 24; });
  source.resize(mesh.cell_count());
  std::iota(source.begin(), source.end(), 0u);
  if (!any) return 0;
  VolumeMesh linear;
  std::vector<uint32_t> from;
  int64_t count = 0;
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    const auto v = mesh.cell(c);
    const uint8_t type = mesh.cell_types[c];
    if (type == kQuadraticTetra) {
      for (const auto& t : kQuadraticTetraSplit) {
        const std::array<uint32_t, 4> tet = {v[t[0]], v[t[1]], v[t[2]], v[t[3]]};
        linear.AddCell(CellType::kTetrahedron, tet);
        from.push_back(static_cast<uint32_t>(c));
      }
    } else if (type >= 24) {
      const CellType corners = LinearOf(type);
      linear.AddCell(corners, v.first(static_cast<size_t>(CellVertexCount(static_cast<uint8_t>(corners)))));
      from.push_back(static_cast<uint32_t>(c));
    } else {
      linear.AddCell(static_cast<CellType>(type), v);
      from.push_back(static_cast<uint32_t>(c));
    }
    count += type >= 24;
  }
  mesh.cell_types = std::move(linear.cell_types);
  mesh.cell_offsets = std::move(linear.cell_offsets);
  mesh.cell_vertices = std::move(linear.cell_vertices);
  source = std::move(from);
  return count;
}

bool Missing(const VertexField& f, size_t vertex) {
  for (int k = 0; k < f.components; ++k) {
    if (!std::isfinite(f.values[vertex * static_cast<size_t>(f.components) + static_cast<size_t>(k)])) return true;
  }
  return false;
}

// Refuses a field whose share of missing vertices is beyond `max_share`, naming the count and the
// first; returns the number of vertices missing any value.
absl::StatusOr<int64_t> CountMissing(const VolumeMesh& mesh, double max_share) {
  const size_t n = mesh.vertex_count();
  std::vector<bool> any(n, false);
  for (const VertexField& f : mesh.fields) {
    size_t count = 0, first = n;
    for (size_t i = 0; i < n; ++i) {
      if (!Missing(f, i)) continue;
      any[i] = true;
      if (count++ == 0) first = i;
    }
    if (static_cast<double>(count) > max_share * static_cast<double>(n)) {
      return absl::InvalidArgumentError(core::StrCat(
          "field '", f.name, "' is NaN or infinite at ", count, " of ", n, " vertices (the first: vertex ", first,
          "), more than the ", max_share * 100, " % that can be filled in from neighbouring vertices"));
    }
  }
  return static_cast<int64_t>(std::count(any.begin(), any.end(), true));
}

// Keeps the vertices whose `keep` is set, renumbering the cells (which must use none of the others).
void KeepVertices(VolumeMesh& mesh, const std::vector<bool>& keep) {
  const size_t n = mesh.vertex_count();
  std::vector<uint32_t> renumber(n, 0);
  size_t next = 0;
  for (size_t i = 0; i < n; ++i) {
    if (!keep[i]) continue;
    renumber[i] = static_cast<uint32_t>(next);
    mesh.positions[next] = mesh.positions[i];
    for (VertexField& f : mesh.fields) {
      const auto k = static_cast<size_t>(f.components);
      std::copy_n(f.values.begin() + static_cast<std::ptrdiff_t>(i * k), k,
                  f.values.begin() + static_cast<std::ptrdiff_t>(next * k));
    }
    ++next;
  }
  mesh.positions.resize(next);
  for (VertexField& f : mesh.fields) f.values.resize(next * static_cast<size_t>(f.components));
  for (uint32_t& v : mesh.cell_vertices) v = renumber[v];
}

// Vertices at the same position become one, holding the mean of their finite values; returns
// how many were merged into another.
int64_t MergeDuplicates(VolumeMesh& mesh) {
  const size_t n = mesh.vertex_count();
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  auto less = [&](uint32_t a, uint32_t b) {
    const Vec3f &p = mesh.positions[a], &q = mesh.positions[b];
    if (p.x() != q.x()) return p.x() < q.x();
    if (p.y() != q.y()) return p.y() < q.y();
    if (p.z() != q.z()) return p.z() < q.z();
    return a < b;
  };
  std::sort(order.begin(), order.end(), less);
  std::vector<uint32_t> into(n);
  std::iota(into.begin(), into.end(), 0u);
  int64_t merged = 0;
  for (size_t begin = 0; begin < n;) {
    size_t end = begin + 1;
    while (end < n && mesh.positions[order[end]] == mesh.positions[order[begin]]) ++end;
    if (end - begin > 1) {
      const uint32_t keep = order[begin];  // The lowest index of the group.
      for (VertexField& f : mesh.fields) {
        const auto k = static_cast<size_t>(f.components);
        for (size_t c = 0; c < k; ++c) {
          double sum = 0;
          int finite = 0;
          for (size_t g = begin; g < end; ++g) {
            const float value = f.values[order[g] * k + c];
            if (std::isfinite(value)) sum += value, ++finite;
          }
          f.values[keep * k + c] = finite > 0 ? static_cast<float>(sum / finite) : std::nanf("");
        }
      }
      for (size_t g = begin + 1; g < end; ++g) into[order[g]] = keep;
      merged += static_cast<int64_t>(end - begin - 1);
    }
    begin = end;
  }
  if (merged == 0) return 0;
  for (uint32_t& v : mesh.cell_vertices) v = into[v];
  std::vector<bool> keep(n);
  for (size_t i = 0; i < n; ++i) keep[i] = into[i] == i;
  KeepVertices(mesh, keep);
  return merged;
}

// Terms of the local polynomial at offset d: 1, x, y, z and, for a quadratic, the six products.
Eigen::VectorXd Terms(const Eigen::Vector3d& d, int terms) {
  Eigen::VectorXd t(terms);
  t.head<4>() << 1, d.x(), d.y(), d.z();
  if (terms == 10)
    t.tail<6>() << d.x() * d.x(), d.y() * d.y(), d.z() * d.z(), d.x() * d.y(), d.y() * d.z(), d.z() * d.x();
  return t;
}

// A vertex outside the box of its known neighbours (the front of a hole, filled from one side)
// takes no value beyond theirs: a fit extrapolated there, ring after ring into a deep hole,
// grows without bound (to infinity across 36 rings of a half-missing block). Inside the box
// (neighbours all round) the fit is kept as it is, exact on quadratic fields.
void ClampWhereOneSided(const VolumeMesh& mesh, const VertexField& f, uint32_t i, std::span<const uint32_t> near,
                        std::vector<float>& out) {
  Box3 around;
  for (uint32_t j : near) around.extend(mesh.positions[j].cast<double>());
  if (around.contains(mesh.positions[i].cast<double>())) return;
  const auto k = static_cast<size_t>(f.components);
  for (size_t c = 0; c < k; ++c) {
    float lo = std::numeric_limits<float>::infinity(), hi = -lo;
    for (uint32_t j : near) {
      lo = std::min(lo, f.values[j * k + c]);
      hi = std::max(hi, f.values[j * k + c]);
    }
    out[c] = std::clamp(out[c], lo, hi);
  }
}

// The value at vertex i of the polynomial fitted by weighted least squares (weights 1/d^2) to
// the known values at `near`: quadratic where at least 12 neighbours have values, linear where
// 4 do (exact on linear fields), else, or where the neighbours do not span space, their
// inverse-distance mean.
std::vector<float> LocalFitValue(const VolumeMesh& mesh, const VertexField& f, uint32_t i,
                                 std::span<const uint32_t> near) {
  const auto k = static_cast<size_t>(f.components);
  std::vector<double> mean(k, 0.0);
  double weights = 0, reach = 1e-30;
  for (uint32_t j : near) reach = std::max(reach, static_cast<double>((mesh.positions[j] - mesh.positions[i]).norm()));
  std::vector<float> out(k);
  for (const int terms : {10, 4}) {
    if (near.size() < (terms == 10 ? 12u : 4u)) continue;
    Eigen::MatrixXd normal = Eigen::MatrixXd::Zero(terms, terms);
    Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(terms, static_cast<Eigen::Index>(k));
    for (uint32_t j : near) {
      // Offsets in units of the farthest neighbour, so that the system's conditioning means shape.
      const Eigen::Vector3d d = (mesh.positions[j] - mesh.positions[i]).cast<double>() / reach;
      const double w = 1.0 / std::max(1e-30, d.squaredNorm());
      const Eigen::VectorXd row = Terms(d, terms);
      normal += w * row * row.transpose();
      for (size_t c = 0; c < k; ++c) rhs.col(static_cast<Eigen::Index>(c)) += w * f.values[j * k + c] * row;
    }
    const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> spread(normal, Eigen::EigenvaluesOnly);
    if (!(spread.eigenvalues()[0] > 1e-8 * spread.eigenvalues()[terms - 1])) continue;
    const Eigen::MatrixXd solution = normal.ldlt().solve(rhs);
    for (size_t c = 0; c < k; ++c) out[c] = static_cast<float>(solution(0, static_cast<Eigen::Index>(c)));
    ClampWhereOneSided(mesh, f, i, near, out);
    return out;
  }
  for (uint32_t j : near) {
    const double w = 1.0 / std::max(1e-30, static_cast<double>((mesh.positions[j] - mesh.positions[i]).norm()));
    for (size_t c = 0; c < k; ++c) mean[c] += w * f.values[j * k + c];
    weights += w;
  }
  for (size_t c = 0; c < k; ++c) out[c] = static_cast<float>(mean[c] / weights);
  return out;
}

// Fills the missing values of a field from the vertices sharing a cell with them, ring by ring
// inwards from the data (LocalFitValue), so that a hole is bridged by its rim.
absl::Status FillFromNeighbours(VolumeMesh& mesh) {
  const size_t n = mesh.vertex_count();
  std::vector<uint32_t> start(n + 1, 0), neighbor;
  {
    std::vector<std::vector<uint32_t>> lists(n);
    for (size_t c = 0; c < mesh.cell_count(); ++c) {
      const auto v = mesh.cell(c);
      for (uint32_t a : v) {
        for (uint32_t b : v) {
          if (a != b) lists[a].push_back(b);
        }
      }
    }
    for (size_t i = 0; i < n; ++i) {
      std::sort(lists[i].begin(), lists[i].end());
      lists[i].erase(std::unique(lists[i].begin(), lists[i].end()), lists[i].end());
      start[i + 1] = start[i] + static_cast<uint32_t>(lists[i].size());
      neighbor.insert(neighbor.end(), lists[i].begin(), lists[i].end());
    }
  }
  // Ring by ring as a breadth-first search: a ring's candidates are the missing neighbours of
  // the ring filled before it, so each vertex and edge is visited a bounded number of times
  // (scanning every missing vertex each ring made a long hole quadratic).
  for (VertexField& f : mesh.fields) {
    const auto k = static_cast<size_t>(f.components);
    std::vector<bool> known(n, true);
    size_t unknown = 0;
    for (size_t i = 0; i < n; ++i) {
      if (Missing(f, i)) {
        known[i] = false;
        ++unknown;
      }
    }
    std::vector<uint32_t> ring;
    std::vector<uint32_t> queued_in_round(n, UINT32_MAX);
    auto queue_missing_neighbours = [&](uint32_t i, uint32_t round, std::vector<uint32_t>& into) {
      for (uint32_t e = start[i]; e < start[i + 1]; ++e) {
        const uint32_t j = neighbor[e];
        if (!known[j] && queued_in_round[j] != round) {
          queued_in_round[j] = round;
          into.push_back(j);
        }
      }
    };
    for (uint32_t i = 0; i < n; ++i) {
      if (known[i]) queue_missing_neighbours(i, 0, ring);
    }
    std::vector<uint32_t> known_near;
    for (uint32_t round = 1; !ring.empty(); ++round) {
      std::vector<std::pair<uint32_t, std::vector<float>>> filled;
      filled.reserve(ring.size());
      for (uint32_t i : ring) {
        known_near.clear();
        for (uint32_t e = start[i]; e < start[i + 1]; ++e) {
          if (known[neighbor[e]]) known_near.push_back(neighbor[e]);
        }
        filled.emplace_back(i, LocalFitValue(mesh, f, i, known_near));
      }
      ring.clear();
      for (auto& [i, value] : filled) {
        std::copy(value.begin(), value.end(), f.values.begin() + static_cast<std::ptrdiff_t>(i * k));
        known[i] = true;
      }
      unknown -= filled.size();
      for (const auto& entry : filled) queue_missing_neighbours(entry.first, round, ring);
    }
    if (unknown > 0) {
      const auto first = static_cast<size_t>(std::find(known.begin(), known.end(), false) - known.begin());
      return absl::InvalidArgumentError(
          core::StrCat("field '", f.name, "' has no value anywhere in a part of the mesh (", unknown,
                       " vertices, among them vertex ", first, " after merging duplicates)"));
    }
  }
  return absl::OkStatus();
}

// The same cell in the other orientation (VTK's order mirrored).
void Mirror(uint8_t type, std::span<uint32_t> v) {
  switch (static_cast<CellType>(type)) {
    case CellType::kTetrahedron: std::swap(v[1], v[2]); break;
    case CellType::kHexahedron: std::swap_ranges(v.begin(), v.begin() + 4, v.begin() + 4); break;
    case CellType::kWedge: std::swap_ranges(v.begin(), v.begin() + 3, v.begin() + 3); break;
    case CellType::kPyramid: std::swap(v[1], v[3]); break;
  }
}

}  // namespace

bool IsQuadraticCell(uint8_t vtk_type) { return vtk_type >= kQuadraticTetra && vtk_type <= kQuadraticPyramid; }

absl::StatusOr<int64_t> FillMissingValues(VolumeMesh& mesh, const VolumeRepairParams& params) {
  LSQSURF_ASSIGN_OR_RETURN(const int64_t missing, CountMissing(mesh, params.max_missing_share));
  if (missing == 0) return 0;
  if (mesh.has_cells()) {
    LSQSURF_RETURN_IF_ERROR(FillFromNeighbours(mesh));
    return missing;
  }
  // A scattered point without a value is no data at all.
  std::vector<bool> keep(mesh.vertex_count(), true);
  for (size_t i = 0; i < mesh.vertex_count(); ++i) {
    for (const VertexField& f : mesh.fields) keep[i] = keep[i] && !Missing(f, i);
  }
  KeepVertices(mesh, keep);
  return missing;
}

absl::StatusOr<VolumeRepairs> RepairVolumeMesh(VolumeMesh& mesh, const VolumeRepairParams& params) {
  LSQSURF_RETURN_IF_ERROR(CheckVolumeStructure(mesh, kNoVolumeLimits));
  // Refused before anything moves, so that the first missing vertex is named as uploaded.
  LSQSURF_RETURN_IF_ERROR(CountMissing(mesh, params.max_missing_share).status());
  VolumeRepairs out;
  std::vector<uint32_t> source;
  out.linearised_cells = Linearise(mesh, source);
  // Merged first, so that a point whose cells all use a copy of it is not taken for unused.
  out.merged_vertices = MergeDuplicates(mesh);
  if (mesh.has_cells()) {
    // Unused points (a quadratic hexahedron's edge nodes among them) have no cell to fill from.
    std::vector<bool> used(mesh.vertex_count(), false);
    for (uint32_t v : mesh.cell_vertices) used[v] = true;
    out.unused_vertices = static_cast<int64_t>(std::count(used.begin(), used.end(), false));
    if (out.unused_vertices > 0) KeepVertices(mesh, used);
  }
  LSQSURF_ASSIGN_OR_RETURN(out.missing_vertices, FillMissingValues(mesh, params));
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    const CellExtent extent = MeasureCell(mesh, c);
    if (extent.longest == 0) {
      return absl::InvalidArgumentError(core::StrCat("cell ", source[c], " (", CellTypeName(mesh.cell_types[c]),
                                                     "): all its corners lie at one point"));
    }
    if (extent.degenerate()) {
      ++out.degenerate_cells;
    } else if (extent.volume < 0) {
      Mirror(mesh.cell_types[c], {mesh.cell_vertices.data() + mesh.cell_offsets[c], mesh.cell(c).size()});
      ++out.reoriented_cells;
    }
  }
  return out;
}

}  // namespace lsqsurf::core
