#include "worker/jobs/surface_points.h"

#include <chrono>
#include <cmath>
#include <limits>
#include <string_view>

#include "worker/core/attribute_transfer.h"
#include "worker/core/geometry.h"
#include "worker/core/kd_tree.h"
#include "worker/core/local_spacing.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/hole_filling.h"

namespace lsqsurf::jobs {
namespace {

constexpr int kMaxViewpoints = 4096;  // Scanner stations of one job.

}  // namespace

const core::ParamTable<PointParams>& PointParamsTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<PointParams>();
    t->Flag<&PointParams::estimate_normals>("estimate_normals",
                                            "estimate normals when the cloud has none (PCA + spanning-tree "
                                            "orientation); false rejects clouds without normals")
        .Integer<&PointParams::normal_neighbors>("normal_neighbors", 3, 128, "points",
                                                 "nearest neighbours of the normal estimate (2, 4 or 8 "
                                                 "times as many where these do not lie flat)")
        .RealList<&PointParams::viewpoint>(
            "viewpoint", 3 * kMaxViewpoints, -std::numeric_limits<double>::infinity(),
            std::numeric_limits<double>::infinity(), "model units",
            "where the sensor stood (x,y,z): estimated normals face it; several x,y,z: one per scan, each "
            "point's attribute scan naming its own; empty = unknown (oriented by propagation); the client "
            "sets it from a PCD file's VIEWPOINT and a PTX file's scanner positions")
        .Text<&PointParams::point_attributes>(
            "point_attributes",
            "per-point attributes of the cloud carried to the mesh vertices, by name, comma-separated; empty = "
            "colour (red,green,blue) and intensity, those the cloud has; none = none")
        .Flag<&PointParams::fill_holes>(
            "fill_holes",
            "close the holes the data leave (smooth patches spanning each border), so the mesh is closed; "
            "vertex attribute filled = 1 where a vertex lies farther than 3 spacings from every point "
            "(statistics holes_filled, holes_left)")
        .Flag<&PointParams::remove_outliers>(
            "remove_outliers",
            "remove isolated points first (their 8th neighbour 4 times farther than their neighbours' is; "
            "statistic outliers_removed)")
        .AddRule([](const PointParams& p) {
          if (p.viewpoint.size() % 3 == 0) return absl::OkStatus();
          return absl::InvalidArgumentError(
              core::StrCat("viewpoint takes three numbers x,y,z per sensor (or none), not ", p.viewpoint.size()));
        });
    return t;
  }();
  return *table;
}

absl::Status ChooseViewpoints(const PointParams& points, const core::PointCloud& cloud,
                              core::NormalEstimationParams& normals) {
  const size_t count = points.viewpoint.size() / 3;
  for (size_t v = 0; v < count; ++v) {
    normals.viewpoints.emplace_back(points.viewpoint[3 * v], points.viewpoint[3 * v + 1], points.viewpoint[3 * v + 2]);
  }
  if (count <= 1) return absl::OkStatus();
  const core::ScalarAttribute* scan = nullptr;
  for (const core::ScalarAttribute& a : cloud.attributes) {
    if (a.name == "scan" && a.values.size() == cloud.size()) scan = &a;
  }
  if (scan == nullptr) {
    return absl::InvalidArgumentError(core::StrCat("viewpoint gives ", count,
                                                   " sensor positions, but the cloud has no per-point attribute "
                                                   "scan saying which saw each point"));
  }
  normals.station.reserve(cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    const float s = scan->values[i];
    if (!(s >= 0) || s >= static_cast<float>(count) || s != std::floor(s)) {
      return absl::InvalidArgumentError(core::StrCat("point ", i, "'s scan is ", s, ", not one of the ", count,
                                                     " sensor positions viewpoint gives (0 to ", count - 1, ")"));
    }
    normals.station.push_back(static_cast<uint32_t>(s));
  }
  return absl::OkStatus();
}

absl::Status CarryPointAttributes(const PointParams& points, const core::PointCloud& cloud, core::JobContext& ctx,
                                  core::TriangleMesh& mesh, Statistics& statistics) {
  std::vector<std::string> names;
  if (points.point_attributes.empty()) {
    names = core::DefaultCarriedAttributes(cloud);
  } else if (points.point_attributes != "none") {
    for (std::string_view rest = points.point_attributes; !rest.empty();) {
      const size_t comma = rest.find(',');
      std::string_view name = rest.substr(0, comma);
      rest = comma == std::string_view::npos ? std::string_view() : rest.substr(comma + 1);
      while (!name.empty() && name.front() == ' ') name.remove_prefix(1);
      while (!name.empty() && name.back() == ' ') name.remove_suffix(1);
      if (!name.empty()) names.emplace_back(name);
    }
  }
  if (names.empty()) return absl::OkStatus();
  const auto start = std::chrono::steady_clock::now();
  LSQSURF_RETURN_IF_ERROR(core::CarryAttributes(cloud, names, mesh, ctx));
  statistics.emplace_back("carried_attributes", static_cast<double>(names.size()));
  statistics.emplace_back("carry_seconds", core::SecondsSince(start));
  return absl::OkStatus();
}

core::ScalarAttribute UnmeasuredVertices(const core::PointCloud& cloud, const core::TriangleMesh& mesh,
                                         core::JobContext& ctx) {
  core::ScalarAttribute filled{kFilledAttribute, std::vector<float>(mesh.vertices.size(), 0.0f)};
  if (cloud.size() < 2) return filled;
  const core::KdTree tree(cloud.positions);
  const core::LocalSpacing spacing(tree, &ctx);
  // Errors are cancellation only, which the caller checks next.
  (void)core::ParallelFor(
      mesh.vertices.size(), 4096,
      [&](size_t begin, size_t end) {
        std::vector<core::Neighbor> found;
        for (size_t v = begin; v < end; ++v) {
          if (spacing.At(mesh.vertices[v], found).Unmeasured()) filled.values[v] = 1;
        }
      },
      &ctx);
  return filled;
}

int64_t RemoveInventedInnerShells(core::TriangleMesh& mesh, std::span<const float> unmeasured) {
  uint32_t count = 0;
  const std::vector<uint32_t> component = core::ComponentOfFaces(mesh, count);
  if (count < 2) return 0;
  struct Part {
    double area = 0, unmeasured = 0;
    core::Box3 box;
    uint32_t first_face = UINT32_MAX;
  };
  std::vector<Part> parts(count);
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    const core::Triangle& t = mesh.faces[f];
    const core::Vec3d a = mesh.vertices[t[0]].cast<double>(), b = mesh.vertices[t[1]].cast<double>(),
                      c = mesh.vertices[t[2]].cast<double>();
    const double area = 0.5 * (b - a).cross(c - a).norm();
    Part& part = parts[component[f]];
    part.area += area;
    // A face is unmeasured where most of its vertices are.
    if (unmeasured[t[0]] + unmeasured[t[1]] + unmeasured[t[2]] >= 1.5f) part.unmeasured += area;
    for (uint32_t v : t) part.box.extend(mesh.vertices[v].cast<double>());
    if (part.first_face == UINT32_MAX) part.first_face = f;
  }
  std::vector<char> drop(mesh.faces.size(), 0), around(mesh.faces.size(), 0);
  int64_t removed = 0;
  for (uint32_t c = 0; c < count; ++c) {
    const Part& shell = parts[c];
    if (!(shell.unmeasured > kInventedShellShare * shell.area)) continue;
    const core::Triangle& t = mesh.faces[shell.first_face];
    const core::Vec3d probe =
        (mesh.vertices[t[0]].cast<double>() + mesh.vertices[t[1]].cast<double>() + mesh.vertices[t[2]].cast<double>()) /
        3;
    // The larger components whose box holds the shell may enclose it.
    bool any = false;
    for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
      const Part& other = parts[component[f]];
      around[f] = component[f] != c && other.area > shell.area && other.box.contains(shell.box);
      any |= around[f] != 0;
    }
    if (!any || std::abs(core::WindingNumber(mesh, around, probe)) < 0.5) continue;
    for (uint32_t f = 0; f < mesh.faces.size(); ++f) drop[f] |= component[f] == c;
    ++removed;
  }
  if (removed > 0) core::RemoveFaces(mesh, drop);
  return removed;
}

absl::Status CloseHolesOnRequest(const PointParams& points, const core::PointCloud& cloud, core::JobContext& ctx,
                                 core::TriangleMesh& mesh, Statistics& statistics) {
  if (!points.fill_holes) return absl::OkStatus();
  const auto start = std::chrono::steady_clock::now();
  // In an order of the surface alone, so that the same cloud gets the same filling on every run.
  core::SortMeshByPosition(mesh);
  auto filled = extract::FillHoles(mesh, {}, ctx);
  if (!filled.ok()) return filled.status();
  mesh.vertex_attributes.push_back(UnmeasuredVertices(cloud, mesh, ctx));
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  const int64_t shells = RemoveInventedInnerShells(mesh, mesh.vertex_attributes.back().values);
  double marked = 0;
  for (float f : mesh.vertex_attributes.back().values) marked += f;
  statistics.emplace_back("holes_filled", static_cast<double>(filled->holes_filled));
  statistics.emplace_back("holes_left", static_cast<double>(filled->holes_left));
  statistics.emplace_back("holes_unfaired", static_cast<double>(filled->unfaired));
  statistics.emplace_back("fill_vertices", static_cast<double>(filled->vertices_added));
  statistics.emplace_back("filled_vertices", marked);
  statistics.emplace_back("inner_shells_removed", static_cast<double>(shells));
  statistics.emplace_back("fill_seconds", core::SecondsSince(start));
  return absl::OkStatus();
}

}  // namespace lsqsurf::jobs
