#include "worker/jobs/surface_points.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <optional>
#include <string_view>
#include <vector>

#include "worker/core/attribute_transfer.h"
#include "worker/core/depth_steps.h"
#include "worker/core/geometry.h"
#include "worker/core/kd_tree.h"
#include "worker/core/local_spacing.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/normals.h"
#include "worker/core/outliers.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/extract/hole_filling.h"

namespace lsqsurf::jobs {
namespace {

constexpr int kMaxViewpoints = 4096;  // Scanner stations of one job.

// Whether the measured vertices of `faces` lie on the faces marked in `around` (median distance
// to their vertices within kShellOnSurfaceEdges median edges of `faces`), or there are none:
// the data such a shell covers is covered already.
bool MeasuredPartLiesOn(const core::TriangleMesh& mesh, std::span<const float> unmeasured,
                        std::span<const uint32_t> faces, std::span<const char> around) {
  std::vector<char> on_around(mesh.vertices.size(), 0), measured(mesh.vertices.size(), 0);
  std::vector<double> edges;
  edges.reserve(faces.size());
  for (uint32_t f : faces) {
    const core::Triangle& t = mesh.faces[f];
    edges.push_back((mesh.vertices[t[1]] - mesh.vertices[t[0]]).norm());
    for (uint32_t v : t) measured[v] = unmeasured[v] < 0.5f;
  }
  std::vector<core::Vec3f> targets;
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    if (!around[f]) continue;
    for (uint32_t v : mesh.faces[f]) {
      if (!on_around[v]) targets.push_back(mesh.vertices[v]);
      on_around[v] = 1;
    }
  }
  std::vector<double> distances;
  const core::KdTree tree(targets);
  for (uint32_t v = 0; v < mesh.vertices.size(); ++v) {
    if (measured[v]) distances.push_back(std::sqrt(tree.Nearest(mesh.vertices[v]).distance2));
  }
  if (distances.empty()) return true;
  auto median = [](std::vector<double>& values) {
    std::ranges::nth_element(values, values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2));
    return values[values.size() / 2];
  };
  return median(distances) <= kShellOnSurfaceEdges * median(edges);
}

// core::UndoDepthSteps on the points of each sensor position in turn, or on all of them where none
// is given; returns whether the steps placed the sensor at the origin then.
absl::StatusOr<bool> UndoDepthStepsPerScan(const PointParams& points, core::PointCloud& cloud, core::JobContext& ctx,
                                           Statistics& statistics) {
  core::NormalEstimationParams sensors;
  LSQSURF_RETURN_IF_ERROR(ChooseViewpoints(points, cloud, sensors));
  std::vector<std::vector<uint32_t>> scans(std::max<size_t>(1, sensors.viewpoints.size()));
  for (uint32_t i = 0; i < cloud.size(); ++i) scans[sensors.station.empty() ? 0 : sensors.station[i]].push_back(i);
  size_t moved = 0, stepped = 0;
  double step = 0;
  bool inferred = false;
  std::vector<core::Vec3f> scan_points;
  for (size_t s = 0; s < scans.size(); ++s) {
    scan_points.clear();
    for (uint32_t i : scans[s]) scan_points.push_back(cloud.positions[i]);
    const std::optional<core::Vec3d> eye =
        sensors.viewpoints.empty() ? std::nullopt : std::optional(sensors.viewpoints[s]);
    auto undone = core::UndoDepthSteps(scan_points, eye, {}, ctx);
    if (!undone.ok()) return undone.status();
    if (!undone->found) continue;
    for (size_t k = 0; k < scans[s].size(); ++k) cloud.positions[scans[s][k]] = scan_points[k];
    moved += undone->moved;
    step = std::max(step, undone->step);
    inferred = undone->eye_inferred;
    ++stepped;
  }
  if (stepped == 0) return false;
  statistics.emplace_back("depth_step", step);
  statistics.emplace_back("depth_steps_moved", static_cast<double>(moved) / static_cast<double>(cloud.size()));
  if (inferred) statistics.emplace_back("viewpoint_inferred", 1);
  return inferred;
}

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
            core::StrCat("where the sensor stood (x,y,z): estimated normals face it; several x,y,z: one per scan, "
                         "each point's attribute scan naming its own; empty = unknown (oriented by propagation, as "
                         "also where over ",
                         100 * core::NormalEstimationParams{}.max_hidden_share,
                         " % of the points are hidden from their sensor: statistic viewpoint_hidden_share); the "
                         "client sets it from a PCD file's VIEWPOINT and a PTX file's scanner positions"))
        .Text<&PointParams::point_attributes>(
            "point_attributes",
            "per-point attributes of the cloud carried to the mesh vertices, by name, comma-separated; empty = "
            "colour (red,green,blue) and intensity, those the cloud has; none = none")
        .Flag<&PointParams::fill_holes>(
            "fill_holes",
            "close the holes the data leave (smooth patches spanning each border), so the mesh is closed; "
            "vertex attribute filled = 1 where a vertex lies farther than 3 spacings from every point "
            "(statistics holes_filled, holes_left)")
        .Flag<&PointParams::undo_depth_steps>(
            "undo_depth_steps",
            "where the points lie on quantized depth levels (stereo disparity, depth-camera steps: many "
            "neighbourhoods exactly flat, nearly all square to one direction or to the line of sight, on 8 "
            "levels or more), move each point along its ray from the viewpoint, by at most half a step, onto a "
            "plane fitted across the steps around it (statistics depth_step, depth_steps_moved); with no "
            "viewpoint, where disparity steps place the sensor at the origin (a camera's own frame), it is "
            "taken as the viewpoint (statistic viewpoint_inferred)")
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

absl::StatusOr<double> PrepareSurfaceCloud(const PointParams& points, core::PointCloud& cloud, core::JobContext& ctx,
                                           Statistics& statistics) {
  if (const size_t repeats = core::RemoveDuplicatePoints(cloud); repeats > 0) {
    statistics.emplace_back("duplicate_points", static_cast<double>(repeats));
    if (cloud.size() < 4) {
      return absl::InvalidArgumentError(core::StrCat("the cloud holds only ", cloud.size(), " distinct positions (",
                                                     repeats,
                                                     " points repeat another's exactly); a surface needs more"));
    }
  }

  if (points.remove_outliers) {
    auto removed = core::RemoveIsolatedPoints(cloud, {}, ctx);
    if (!removed.ok()) return removed.status();
    if (*removed > 0) statistics.emplace_back("outliers_removed", static_cast<double>(*removed));
  }

  PointParams seen = points;  // With the sensor's position where the depth steps place it.
  if (points.undo_depth_steps) {
    auto inferred = UndoDepthStepsPerScan(points, cloud, ctx, statistics);
    if (!inferred.ok()) return inferred.status();
    if (*inferred) seen.viewpoint = {0, 0, 0};
  }

  if (!cloud.has_normals()) {
    if (!points.estimate_normals) {
      return absl::InvalidArgumentError("the cloud has no normals and estimate_normals is false");
    }
    const auto start = std::chrono::steady_clock::now();
    core::SubContext sub(ctx, "estimating normals", 0.0, kNormalsShare);
    core::NormalEstimationParams np;
    np.neighbors = points.normal_neighbors;
    LSQSURF_RETURN_IF_ERROR(ChooseViewpoints(seen, cloud, np));
    core::NormalOrientation orientation;
    auto estimated = core::EstimateNormals(cloud.positions, np, sub, &orientation);
    if (!estimated.ok()) return estimated.status();
    if (!np.viewpoints.empty()) {
      statistics.emplace_back("normals_toward_viewpoint",
                              orientation.toward_viewpoints ? static_cast<double>(np.viewpoints.size()) : 0.0);
      statistics.emplace_back("viewpoint_hidden_share", orientation.hidden_share);
    }
    cloud.normals = *std::move(estimated);
    statistics.emplace_back("normals_seconds", core::SecondsSince(start));
    return kNormalsShare;
  }
  return 0.0;
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
    std::vector<uint32_t> faces;
  };
  std::vector<Part> parts(count);
  for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
    const core::Triangle& t = mesh.faces[f];
    Part& part = parts[component[f]];
    const double area = core::FaceArea(mesh, t);
    part.area += area;
    if (core::FaceUnmeasured(unmeasured, t)) part.unmeasured += area;
    for (uint32_t v : t) part.box.extend(mesh.vertices[v].cast<double>());
    part.faces.push_back(f);
  }
  std::vector<char> drop(mesh.faces.size(), 0), around(mesh.faces.size(), 0);
  int64_t removed = 0;
  for (uint32_t c = 0; c < count; ++c) {
    const Part& shell = parts[c];
    if (!(shell.unmeasured > kInventedShellShare * shell.area)) continue;
    // Probes at faces spread over the shell: an invented shell may cross the surface around it
    // where the two were fitted to the same points, and one probe there reads 0.
    std::vector<core::Vec3d> probes;
    const size_t stride = std::max<size_t>(1, shell.faces.size() / kShellProbes);
    for (size_t k = 0; k < shell.faces.size() && probes.size() < kShellProbes; k += stride) {
      const core::Triangle& t = mesh.faces[shell.faces[k]];
      probes.push_back((mesh.vertices[t[0]].cast<double>() + mesh.vertices[t[1]].cast<double>() +
                        mesh.vertices[t[2]].cast<double>()) /
                       3);
    }
    // The larger components whose box meets the shell's may enclose it.
    bool any = false;
    for (uint32_t f = 0; f < mesh.faces.size(); ++f) {
      const Part& other = parts[component[f]];
      around[f] = component[f] != c && other.area > shell.area && other.box.intersects(shell.box);
      any |= around[f] != 0;
    }
    if (!any) continue;
    const std::vector<double> winding = core::WindingNumbers(mesh, around, probes);
    const auto inside =
        static_cast<size_t>(std::ranges::count_if(winding, [](double w) { return std::abs(w) >= 0.5; }));
    const bool enclosed = 2 * inside > probes.size();
    if (!enclosed && !(inside > 0 && MeasuredPartLiesOn(mesh, unmeasured, shell.faces, around))) continue;
    for (uint32_t f : shell.faces) drop[f] = 1;
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
  statistics.emplace_back("holes_umbrella_faired", static_cast<double>(filled->umbrella_faired));
  statistics.emplace_back("fill_vertices", static_cast<double>(filled->vertices_added));
  statistics.emplace_back("filled_vertices", marked);
  statistics.emplace_back("inner_shells_removed", static_cast<double>(shells));
  statistics.emplace_back("fill_seconds", core::SecondsSince(start));
  return absl::OkStatus();
}

}  // namespace lsqsurf::jobs
