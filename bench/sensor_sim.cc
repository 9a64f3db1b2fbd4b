// lsqsurf-sensor-sim — scans of a known mesh as sensors make them, ray-cast with Embree, and the
// report that measures a reconstruction of such a scan against the mesh.
//
//   lsqsurf-sensor-sim depth MESH -o view.pcd [--eye X,Y,Z] [--views K] ...
//   lsqsurf-sensor-sim lidar MESH -o scans.ptx [--stations N] ...
//   lsqsurf-sensor-sim report --truth MESH --scan view.pcd --mesh result.ply [--eye X,Y,Z ...]
//
// depth: a 640×480 pinhole camera (a Kinect-like depth camera or, with --quantum large, a stereo
// rig's layered steps): depth noise σ growing with depth squared, depth quantized in disparity
// (1/z), no return where a ray meets the surface nearer than --grazing-deg to edge-on, colour from
// the mesh's vertex colours or a procedural texture. One view is a PCD with its VIEWPOINT; --views
// K > 1 places K cameras around the object and writes them as the scans of one PTX file, each
// moved by a registration error. lidar: N stations of a terrestrial scanner around the object, a
// full sweep each (azimuth × elevation grid), range noise and registration error, written as PTX
// with each station's position. Lengths are fractions of the mesh's bounding-box diagonal.
//
// report: the share of the reconstruction's area facing a sensor (any of the scan's), components
// and fragments after merging vertices by position, boundary edges, the mean distance from the
// reconstruction to the truth (one-sided: a view sees only part of the mesh), the area farther
// than 3 mean spacings from every scan point (invented), the share of scan points within 2 mean
// spacings of the reconstruction (covered), and the colour error of the mesh's vertices against
// the nearest scan point's colour.
#include <embree3/rtcore.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/core/kd_tree.h"
#include "worker/core/local_spacing.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/strings.h"
#include "worker/core/surface_distance.h"
#include "worker/io/files.h"
#include "worker/io/point_stream.h"
#include "worker/io/pts_ptx.h"
#include "worker/jobs/surface_points.h"

namespace {

using lsqsurf::core::Vec3d;
using lsqsurf::core::Vec3f;
namespace core = lsqsurf::core;
namespace io = lsqsurf::io;

int Fail(const std::string& why) {
  std::fprintf(stderr, "lsqsurf-sensor-sim: %s\n", why.c_str());
  return 1;
}

bool ParseVec(const std::string& text, Vec3d& out) {
  return std::sscanf(text.c_str(), "%lf,%lf,%lf", &out.x(), &out.y(), &out.z()) == 3;
}

// A unit up direction and two unit directions square to it and to each other: the plane the
// sensors circle the object in.
struct Horizon {
  Vec3d up, side, other;
};

bool ParseUp(const std::string& text, Horizon& h) {
  if (!ParseVec(text, h.up) || !(h.up.norm() > 0)) return false;
  h.up.normalize();
  h.side = (std::abs(h.up.x()) < 0.9 ? h.up.cross(Vec3d::UnitX()) : h.up.cross(Vec3d::UnitY())).normalized();
  h.other = h.up.cross(h.side);
  return true;
}

// The mesh in an Embree scene, with what a hit needs to colour itself.
class Scene {
 public:
  explicit Scene(const core::TriangleMesh& mesh) : mesh_(mesh) {
    device_ = rtcNewDevice(nullptr);
    scene_ = rtcNewScene(device_);
    RTCGeometry geometry = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                          3 * sizeof(float), mesh.vertices.size()));
    for (size_t i = 0; i < mesh.vertices.size(); ++i) {
      for (int a = 0; a < 3; ++a) v[3 * i + a] = mesh.vertices[i][a];
    }
    auto* f = static_cast<unsigned*>(rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                             3 * sizeof(unsigned), mesh.faces.size()));
    for (size_t i = 0; i < mesh.faces.size(); ++i) {
      for (int a = 0; a < 3; ++a) f[3 * i + a] = mesh.faces[i][a];
    }
    rtcCommitGeometry(geometry);
    rtcAttachGeometry(scene_, geometry);
    rtcReleaseGeometry(geometry);
    rtcCommitScene(scene_);
    colour_ = core::ColourChannels(mesh.vertex_attributes, mesh.vertices.size());
    const core::Box3 box = core::BoundingBox(mesh.vertices);
    diagonal_ = core::Diagonal(box);
    centre_ = box.center();
  }
  ~Scene() {
    rtcReleaseScene(scene_);
    rtcReleaseDevice(device_);
  }
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;

  struct Hit {
    double t = 0;
    double cosine = 0;  // |cos| between the ray and the face normal.
    std::array<float, 3> rgb{};
  };
  // The first surface along `dir` (unit) from `origin`, if any.
  bool Cast(const Vec3d& origin, const Vec3d& dir, Hit& hit) const {
    RTCIntersectContext context;
    rtcInitIntersectContext(&context);
    RTCRayHit rh{};
    rh.ray.org_x = static_cast<float>(origin.x());
    rh.ray.org_y = static_cast<float>(origin.y());
    rh.ray.org_z = static_cast<float>(origin.z());
    rh.ray.dir_x = static_cast<float>(dir.x());
    rh.ray.dir_y = static_cast<float>(dir.y());
    rh.ray.dir_z = static_cast<float>(dir.z());
    rh.ray.tnear = 0;
    rh.ray.tfar = std::numeric_limits<float>::infinity();
    rh.ray.mask = ~0u;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(scene_, &context, &rh);
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
    hit.t = rh.ray.tfar;
    const Vec3d ng(rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z);
    hit.cosine = ng.norm() > 0 ? std::abs(ng.dot(dir)) / ng.norm() : 0;
    const Vec3d p = origin + hit.t * dir;
    if (colour_[0] != nullptr) {
      const core::Triangle& f = mesh_.faces[rh.hit.primID];
      const float w[3] = {1 - rh.hit.u - rh.hit.v, rh.hit.u, rh.hit.v};
      for (int c = 0; c < 3; ++c) {
        hit.rgb[c] = 0;
        for (int k = 0; k < 3; ++k) hit.rgb[c] += w[k] * colour_[c]->values[f[k]];
      }
    } else {
      hit.rgb = Texture(p);
    }
    return true;
  }
  double diagonal() const { return diagonal_; }
  Vec3d centre() const { return centre_; }

 private:
  // Stripes and a smooth gradient, so that colour has edges and ramps to carry.
  std::array<float, 3> Texture(const Vec3d& p) const {
    const Vec3d q = (p - centre_) / diagonal_;
    const bool stripe = static_cast<int64_t>(std::floor(q.x() * 12 + q.y() * 5)) % 2 == 0;
    const auto ramp = static_cast<float>(std::clamp(0.5 + q.z(), 0.0, 1.0));
    return {stripe ? 220.0f : 40.0f, 255.0f * ramp, stripe ? 60.0f : 200.0f};
  }
  const core::TriangleMesh& mesh_;
  RTCDevice device_;
  RTCScene scene_;
  std::array<const core::ScalarAttribute*, 3> colour_{};
  double diagonal_ = 1;
  Vec3d centre_;
};

// A small rigid error: a rotation of `error` × diagonal / distance radians about a random axis
// through the sensor, and a shift of `error` × diagonal.
struct Misregistration {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Vec3d shift = Vec3d::Zero();
  Vec3d Apply(const Vec3d& p, const Vec3d& about) const { return about + rotation * (p - about) + shift; }
};

Misregistration RandomMisregistration(double error, double diagonal, double distance, std::mt19937_64& rng) {
  Misregistration m;
  if (error <= 0) return m;
  std::normal_distribution<double> normal;
  Vec3d axis(normal(rng), normal(rng), normal(rng));
  Vec3d shift(normal(rng), normal(rng), normal(rng));
  m.rotation = Eigen::AngleAxisd(error * diagonal / distance, axis.normalized()).toRotationMatrix();
  m.shift = shift.normalized() * error * diagonal;
  return m;
}

struct DepthOptions {
  std::string mesh, output;
  std::string eye_text, up_text = "0,1,0";
  int width = 640, height = 480, views = 1;
  double fov_deg = 58;          // Horizontal.
  double distance = 1.2;        // Camera to the mesh centre, in diagonals (when no --eye).
  double noise = 0.0008;        // σ of depth at the centre's distance (grows with depth²).
  double quantum = 0.0015;      // Depth step at the centre's distance (disparity steps: grows with depth²).
  double grazing_deg = 78;      // No return nearer than this to edge-on.
  double registration = 0.001;  // Views after the first (--views > 1).
  uint64_t seed = 1;
};

// One camera's points, with their colour; missing pixels left out.
core::PointCloud DepthView(const Scene& scene, const DepthOptions& o, const Vec3d& eye, const Vec3d& up_hint,
                           std::mt19937_64& rng) {
  const Vec3d forward = (scene.centre() - eye).normalized();
  const Vec3d right = forward.cross(up_hint).normalized();
  const Vec3d up = right.cross(forward);
  const double d0 = (scene.centre() - eye).norm();
  const double half = std::tan(o.fov_deg * M_PI / 360.0);
  const double step_inverse = o.quantum * scene.diagonal() / (d0 * d0);  // Of 1/z.
  const double grazing = std::cos(o.grazing_deg * M_PI / 180.0);
  std::normal_distribution<double> normal;
  core::PointCloud cloud;
  cloud.attributes = {{"red", {}}, {"green", {}}, {"blue", {}}};
  for (int j = 0; j < o.height; ++j) {
    for (int i = 0; i < o.width; ++i) {
      const double sx = ((i + 0.5) / o.width - 0.5) * 2 * half;
      const double sy = -((j + 0.5) / o.height - 0.5) * 2 * half * o.height / o.width;
      const Vec3d dir = (forward + sx * right + sy * up).normalized();
      Scene::Hit hit;
      if (!scene.Cast(eye, dir, hit) || hit.cosine < grazing) continue;
      const double along = dir.dot(forward);
      double z = hit.t * along;
      z += normal(rng) * o.noise * scene.diagonal() * (z / d0) * (z / d0);
      if (step_inverse > 0) z = 1.0 / (std::round((1.0 / z) / step_inverse) * step_inverse);
      const Vec3d p = eye + dir * (z / along);
      cloud.positions.push_back(p.cast<float>());
      for (int c = 0; c < 3; ++c) cloud.attributes[c].values.push_back(std::round(hit.rgb[c]));
    }
  }
  return cloud;
}

int RunDepth(const DepthOptions& o) {
  auto mesh = io::ReadMeshFile(o.mesh);
  if (!mesh.ok()) return Fail(std::string(mesh.status().message()));
  const Scene scene(*mesh);
  Horizon h;
  if (!ParseUp(o.up_text, h)) return Fail("--up takes x,y,z");
  const Vec3d& up = h.up;
  Vec3d first_eye;
  // Around the object in the plane square to `up`, a little above it.
  std::vector<Vec3d> eyes;
  for (int v = 0; v < o.views; ++v) {
    const double angle = 2 * M_PI * v / o.views;
    const Vec3d direction = (std::cos(angle) * h.side + std::sin(angle) * h.other + 0.35 * up).normalized();
    eyes.push_back(scene.centre() + direction * o.distance * scene.diagonal());
  }
  if (!o.eye_text.empty()) {
    if (!ParseVec(o.eye_text, first_eye)) return Fail("--eye takes x,y,z");
    eyes[0] = first_eye;
  }
  std::mt19937_64 rng(o.seed);
  std::vector<core::PointCloud> views;
  for (size_t v = 0; v < eyes.size(); ++v) {
    views.push_back(DepthView(scene, o, eyes[v], up, rng));
    if (v > 0) {
      const Misregistration m =
          RandomMisregistration(o.registration, scene.diagonal(), (eyes[v] - scene.centre()).norm(), rng);
      for (Vec3f& p : views.back().positions) p = m.Apply(p.cast<double>(), eyes[v]).cast<float>();
    }
    std::fprintf(stderr, "view %zu: %zu points from (%g, %g, %g)\n", v, views.back().size(), eyes[v].x(), eyes[v].y(),
                 eyes[v].z());
  }
  if (views.size() == 1) {
    const absl::Status s =
        io::WriteFileAtomically(o.output, io::EncodePcd(views[0], io::PcdEncoding::kBinaryCompressed,
                                                        {eyes[0].x(), eyes[0].y(), eyes[0].z(), 1, 0, 0, 0}));
    return s.ok() ? 0 : Fail(std::string(s.message()));
  }
  std::vector<io::PtxScan> scans;
  for (size_t v = 0; v < views.size(); ++v) scans.push_back({eyes[v], &views[v]});
  const absl::Status s = io::WriteFileAtomically(o.output, io::EncodePtx(scans));
  return s.ok() ? 0 : Fail(std::string(s.message()));
}

struct LidarOptions {
  std::string mesh, output, up_text = "0,1,0";
  int stations = 4;
  int azimuth_steps = 1800, elevation_steps = 900;  // Over 360° and 180°.
  double distance = 1.0;                            // Station to the centre, in diagonals.
  double height = -0.3;                             // Station above the centre along up, in diagonals (a tripod below).
  double range_noise = 0.0005;                      // σ of range.
  double registration = 0.001;                      // Stations after the first.
  double grazing_deg = 85;
  uint64_t seed = 2;
};

int RunLidar(const LidarOptions& o) {
  auto mesh = io::ReadMeshFile(o.mesh);
  if (!mesh.ok()) return Fail(std::string(mesh.status().message()));
  const Scene scene(*mesh);
  Horizon h;
  if (!ParseUp(o.up_text, h)) return Fail("--up takes x,y,z");
  const Vec3d &up = h.up, &side = h.side, &other = h.other;
  std::mt19937_64 rng(o.seed);
  std::normal_distribution<double> normal;
  const double grazing = std::cos(o.grazing_deg * M_PI / 180.0);
  std::vector<core::PointCloud> clouds(o.stations);
  std::vector<Vec3d> stations;
  for (int s = 0; s < o.stations; ++s) {
    const double angle = 2 * M_PI * (s + 0.5) / o.stations;
    const Vec3d station = scene.centre() +
                          (std::cos(angle) * side + std::sin(angle) * other) * o.distance * scene.diagonal() +
                          up * o.height * scene.diagonal();
    stations.push_back(station);
    const Misregistration m =
        s == 0 ? Misregistration{}
               : RandomMisregistration(o.registration, scene.diagonal(), (station - scene.centre()).norm(), rng);
    core::PointCloud& cloud = clouds[s];
    cloud.attributes = {{"red", {}}, {"green", {}}, {"blue", {}}, {"intensity", {}}};
    for (int a = 0; a < o.azimuth_steps; ++a) {
      const double azimuth = 2 * M_PI * a / o.azimuth_steps;
      for (int e = 0; e < o.elevation_steps; ++e) {
        const double elevation = M_PI * ((e + 0.5) / o.elevation_steps - 0.5);
        const Vec3d dir =
            std::cos(elevation) * (std::cos(azimuth) * side + std::sin(azimuth) * other) + std::sin(elevation) * up;
        Scene::Hit hit;
        if (!scene.Cast(station, dir, hit) || hit.cosine < grazing) continue;
        const double range = hit.t + normal(rng) * o.range_noise * scene.diagonal();
        cloud.positions.push_back(m.Apply(station + dir * range, station).cast<float>());
        for (int c = 0; c < 3; ++c) cloud.attributes[c].values.push_back(std::round(hit.rgb[c]));
        cloud.attributes[3].values.push_back(static_cast<float>(hit.cosine));
      }
    }
    std::fprintf(stderr, "station %d: %zu points from (%g, %g, %g)\n", s, cloud.size(), station.x(), station.y(),
                 station.z());
  }
  std::vector<io::PtxScan> scans;
  for (int s = 0; s < o.stations; ++s) scans.push_back({stations[s], &clouds[s]});
  const absl::Status status = io::WriteFileAtomically(o.output, io::EncodePtx(scans));
  return status.ok() ? 0 : Fail(std::string(status.message()));
}

// Where a reconstruction is unmeasured: farther than core::kUnmeasuredSpacings spacings from
// every scan point, by the
// local spacing (the job's own rule for `filled`, core::LocalSpacing) and by the scan's one
// median spacing (which calls a lidar's sparse far side unmeasured).
struct Unmeasured {
  const core::KdTree& points;
  const core::LocalSpacing& local;
  double global_spacing;

  bool Local(const Vec3f& p, std::vector<core::Neighbor>& scratch) const { return local.At(p, scratch).Unmeasured(); }
  bool Global(const Vec3f& p) const {
    return std::sqrt(points.Nearest(p).distance2) > core::kUnmeasuredSpacings * global_spacing;
  }
};

// The area a job marked as filled (vertex attribute `filled`; a face is marked where most of its
// vertices are) against the unmeasured area, by either rule.
struct FilledMarking {
  bool present = false;
  double marked = 0;
  double invented = 0, marked_invented = 0;                // Local rule.
  double invented_global = 0, marked_invented_global = 0;  // Global rule.
};

FilledMarking MeasureFilledMarking(const core::TriangleMesh& mesh, const Unmeasured& unmeasured) {
  FilledMarking m;
  const auto filled = std::ranges::find(mesh.vertex_attributes, std::string("filled"), &core::ScalarAttribute::name);
  if (filled == mesh.vertex_attributes.end()) return m;
  m.present = true;
  std::vector<core::Neighbor> scratch;
  for (const core::Triangle& f : mesh.faces) {
    const Vec3d a = mesh.vertices[f[0]].cast<double>(), b = mesh.vertices[f[1]].cast<double>(),
                c = mesh.vertices[f[2]].cast<double>();
    const double s = 0.5 * (b - a).cross(c - a).norm();
    const Vec3f centre = ((a + b + c) / 3).cast<float>();
    const bool far = unmeasured.Local(centre, scratch), far_global = unmeasured.Global(centre);
    const bool mark = core::FaceUnmeasured(filled->values, f);
    m.marked += mark ? s : 0;
    m.invented += far ? s : 0;
    m.marked_invented += mark && far ? s : 0;
    m.invented_global += far_global ? s : 0;
    m.marked_invented_global += mark && far_global ? s : 0;
  }
  return m;
}

void PrintFilledMarking(const FilledMarking& m, double area) {
  if (!m.present) return;
  // Precision: the share of the marked area that is unmeasured; recall: of the unmeasured area, the
  // share marked.
  auto share = [](double part, double whole) { return whole > 0 ? part / whole : 1.0; };
  std::printf(
      "filled_marked      %.4f\nfilled_precision   %.4f\nfilled_recall      %.4f\n"
      "filled_precision_global %.4f\nfilled_recall_global    %.4f\n",
      m.marked / area, share(m.marked_invented, m.marked), share(m.marked_invented, m.invented),
      share(m.marked_invented_global, m.marked), share(m.marked_invented_global, m.invented_global));
}

struct ReportOptions {
  std::string truth, scan, mesh;
  std::vector<std::string> eyes;
  double fragment = 0.01;  // Components under this share of the area are fragments.
};

int RunReport(const ReportOptions& o) {
  auto truth = io::ReadMeshFile(o.truth);
  if (!truth.ok()) return Fail(std::string(truth.status().message()));
  auto scan = io::ReadPointCloudFile(o.scan);
  if (!scan.ok()) return Fail(std::string(scan.status().message()));
  auto result = io::ReadMeshFile(o.mesh);
  if (!result.ok()) return Fail(std::string(result.status().message()));
  if (result->faces.empty()) return Fail(o.mesh + " has no faces");
  std::vector<Vec3d> eyes;
  for (const std::string& e : o.eyes) {
    if (!ParseVec(e, eyes.emplace_back())) return Fail("--eye takes x,y,z");
  }
  if (eyes.empty()) {  // The sensors the scan file names.
    if (auto stream = io::OpenPointStream(o.scan); stream.ok()) eyes = (*stream)->sensor_positions();
  }
  const double diagonal = core::Diagonal(core::BoundingBox(truth->vertices));
  const core::KdTree points(scan->positions);
  const core::LocalSpacing local_spacing(points);
  const double spacing = local_spacing.MedianNearest();
  const Unmeasured unmeasured{points, local_spacing, spacing};

  const core::TriangleMesh welded = core::WeldByPosition(*result);
  const core::MeshTopology topology = core::AnalyzeTopology(welded);
  // Per face: area, facing, invented, distance to the truth at its centre, component.
  const core::TriangleTree truth_tree(*truth);
  double area = 0, facing = 0, invented = 0, invented_global = 0, distance = 0;
  std::vector<core::Neighbor> scratch;
  std::vector<double> component_area;
  std::vector<int64_t> component(welded.faces.size(), -1);
  {
    // Components by shared vertices (union-find over the welded faces).
    std::vector<uint32_t> parent(welded.vertices.size());
    for (uint32_t i = 0; i < parent.size(); ++i) parent[i] = i;
    auto find = [&](uint32_t x) {
      while (parent[x] != x) x = parent[x] = parent[parent[x]];
      return x;
    };
    for (const core::Triangle& f : welded.faces) {
      parent[find(f[1])] = find(f[0]);
      parent[find(f[2])] = find(f[0]);
    }
    std::vector<int64_t> label(welded.vertices.size(), -1);
    for (size_t i = 0; i < welded.faces.size(); ++i) {
      const uint32_t root = find(welded.faces[i][0]);
      if (label[root] < 0) {
        label[root] = static_cast<int64_t>(component_area.size());
        component_area.push_back(0);
      }
      component[i] = label[root];
    }
  }
  for (size_t i = 0; i < welded.faces.size(); ++i) {
    const core::Triangle& f = welded.faces[i];
    const Vec3d a = welded.vertices[f[0]].cast<double>(), b = welded.vertices[f[1]].cast<double>(),
                c = welded.vertices[f[2]].cast<double>();
    const Vec3d n = (b - a).cross(c - a), centre = (a + b + c) / 3;
    const double s = 0.5 * n.norm();
    area += s;
    component_area[component[i]] += s;
    for (const Vec3d& eye : eyes) {
      if (n.dot(eye - centre) > 0) {
        facing += s;
        break;
      }
    }
    invented += unmeasured.Local(centre.cast<float>(), scratch) ? s : 0;
    invented_global += unmeasured.Global(centre.cast<float>()) ? s : 0;
    distance += s * std::sqrt(truth_tree.Closest(centre).distance2);
  }
  const FilledMarking marking = MeasureFilledMarking(*result, unmeasured);
  double fragments = 0;
  for (double c : component_area) {
    if (c < o.fragment * area) fragments += c;
  }
  // Points covered: within 2 spacings of the reconstruction.
  const core::TriangleTree result_tree(welded);
  size_t covered = 0, checked = 0;
  for (size_t i = 0; i < scan->size(); i += std::max<size_t>(1, scan->size() / 50000), ++checked) {
    if (std::sqrt(result_tree.Closest(scan->positions[i].cast<double>()).distance2) <= 2 * spacing) ++covered;
  }
  // Colour: each vertex's against its nearest scan point's.
  const auto in = core::ColourChannels(scan->attributes, scan->size());
  const auto out = core::ColourChannels(result->vertex_attributes, result->vertices.size());
  std::vector<double> colour_error;
  if (in[0] != nullptr && out[0] != nullptr) {
    for (size_t v = 0; v < result->vertices.size(); v += std::max<size_t>(1, result->vertices.size() / 50000)) {
      const core::Neighbor p = points.Nearest(result->vertices[v]);
      double e = 0;
      for (int c = 0; c < 3; ++c) e = std::max(e, double{std::abs(out[c]->values[v] - in[c]->values[p.index])});
      colour_error.push_back(e);
    }
  }
  std::sort(colour_error.begin(), colour_error.end());
  const double colour_mean = std::accumulate(colour_error.begin(), colour_error.end(), 0.0) /
                             static_cast<double>(std::max<size_t>(colour_error.size(), 1));
  std::printf("scan_points        %zu\nspacing            %.4e\n", scan->size(), spacing / diagonal);
  if (!eyes.empty()) std::printf("facing             %.4f\n", facing / area);
  std::printf(
      "components         %lld\nfragments          %.4f\nboundary_edges     %lld\ninvented           %.4f\n"
      "invented_global    %.4f\ncovered            %.4f\nmesh_to_truth      %.4e\n",
      static_cast<long long>(topology.components), fragments / area, static_cast<long long>(topology.boundary_edges),
      invented / area, invented_global / area,
      static_cast<double>(covered) / static_cast<double>(std::max<size_t>(checked, 1)), distance / area / diagonal);
  // Symmetric: on a partial scan the truth's unseen side counts too, so it compares methods
  // on one scan, and a closed reconstruction against the whole shape.
  core::LocalJobContext ctx;
  if (auto chamfer = core::CompareMeshes(*truth, welded, {.samples = 200'000}, ctx); chamfer.ok()) {
    std::printf("chamfer            %.4e\n", chamfer->chamfer);
  }
  std::printf("watertight         %d\n", topology.watertight() ? 1 : 0);
  PrintFilledMarking(marking, area);
  if (!colour_error.empty()) {
    std::printf("colour_mean        %.2f\ncolour_median      %.0f\ncolour_p90         %.0f\n", colour_mean,
                colour_error[colour_error.size() / 2], colour_error[colour_error.size() * 9 / 10]);
  }
  return 0;
}

struct PrepareOptions {
  std::string scan, output;
};

// The scan as every surface job sees it before its method runs (jobs::PrepareSurfaceCloud with
// the defaults, normals turned toward the sensors the file names, as the client asks), written
// with its normals: a reference method given these gets the same normals as lsqsurf's.
int RunPrepare(const PrepareOptions& o) {
  auto cloud = io::ReadPointCloudFile(o.scan);
  if (!cloud.ok()) return Fail(std::string(cloud.status().message()));
  lsqsurf::jobs::PointParams points;
  if (auto stream = io::OpenPointStream(o.scan); stream.ok()) {
    for (const Vec3d& sensor : (*stream)->sensor_positions())
      points.viewpoint.insert(points.viewpoint.end(), sensor.data(), sensor.data() + 3);
  }
  core::LocalJobContext ctx;
  lsqsurf::jobs::Statistics statistics;
  if (auto prepared = lsqsurf::jobs::PrepareSurfaceCloud(points, *cloud, ctx, statistics); !prepared.ok()) {
    return Fail(std::string(prepared.status().message()));
  }
  for (const auto& [name, value] : statistics) std::printf("%-18s %g\n", name.c_str(), value);
  if (auto written = io::WritePointCloudFile(o.output, *cloud); !written.ok()) {
    return Fail(std::string(written.message()));
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app("Scans of a known mesh as sensors make them, and reports on their reconstructions");
  app.require_subcommand(1);
  DepthOptions depth;
  auto* d = app.add_subcommand("depth", "a depth camera's view (PCD), or several merged (PTX)");
  d->add_option("mesh", depth.mesh, "mesh to scan (PLY, OBJ)")->required();
  d->add_option("-o,--output", depth.output, "the view (.pcd), or the views (.ptx)")->required();
  d->add_option("--eye", depth.eye_text, "the first camera's position x,y,z (default: around the mesh)");
  d->add_option("--up", depth.up_text, "the mesh's up direction")->capture_default_str();
  d->add_option("--views", depth.views, "cameras around the object")->capture_default_str();
  d->add_option("--width", depth.width)->capture_default_str();
  d->add_option("--height", depth.height)->capture_default_str();
  d->add_option("--fov-deg", depth.fov_deg, "horizontal field of view")->capture_default_str();
  d->add_option("--distance", depth.distance, "camera to centre, in diagonals")->capture_default_str();
  d->add_option("--noise", depth.noise, "depth σ at the centre's distance, in diagonals")->capture_default_str();
  d->add_option("--quantum", depth.quantum, "depth step at the centre's distance, in diagonals")->capture_default_str();
  d->add_option("--grazing-deg", depth.grazing_deg, "no return nearer than this to edge-on")->capture_default_str();
  d->add_option("--registration", depth.registration, "registration error of views after the first, in diagonals")
      ->capture_default_str();
  d->add_option("--seed", depth.seed)->capture_default_str();
  LidarOptions lidar;
  auto* l = app.add_subcommand("lidar", "a terrestrial scanner's stations around the object (PTX)");
  l->add_option("mesh", lidar.mesh, "mesh to scan (PLY, OBJ)")->required();
  l->add_option("-o,--output", lidar.output, "the scans (.ptx)")->required();
  l->add_option("--up", lidar.up_text, "the mesh's up direction")->capture_default_str();
  l->add_option("--stations", lidar.stations)->capture_default_str();
  l->add_option("--azimuth-steps", lidar.azimuth_steps)->capture_default_str();
  l->add_option("--elevation-steps", lidar.elevation_steps)->capture_default_str();
  l->add_option("--distance", lidar.distance, "station to centre, in diagonals")->capture_default_str();
  l->add_option("--height", lidar.height, "station above the centre, in diagonals")->capture_default_str();
  l->add_option("--range-noise", lidar.range_noise, "range σ, in diagonals")->capture_default_str();
  l->add_option("--registration", lidar.registration, "registration error of stations after the first")
      ->capture_default_str();
  l->add_option("--seed", lidar.seed)->capture_default_str();
  ReportOptions report;
  auto* r = app.add_subcommand("report", "measures of a reconstruction of a simulated scan");
  r->add_option("--truth", report.truth, "the scanned mesh")->required();
  r->add_option("--scan", report.scan, "the scan")->required();
  r->add_option("--mesh", report.mesh, "the reconstruction")->required();
  r->add_option("--eye", report.eyes, "a sensor's position x,y,z (repeat; default: those the scan file names)");
  r->add_option("--fragment", report.fragment, "components under this share of the area are fragments")
      ->capture_default_str();
  PrepareOptions prepare;
  auto* p =
      app.add_subcommand("prepare", "the scan with the normals a surface job gives it (PLY), for a reference method");
  p->add_option("scan", prepare.scan, "the scan")->required();
  p->add_option("-o,--output", prepare.output, "the points with their normals (.ply)")->required();
  CLI11_PARSE(app, argc, argv);
  if (*d) return RunDepth(depth);
  if (*p) return RunPrepare(prepare);
  if (*l) return RunLidar(lidar);
  return RunReport(report);
}
