// CPU ray casting of a scalar field on a grid; see render.h.
#include <algorithm>
#include <charconv>
#include <cmath>
#include <thread>

#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/render/render.h"
#include "worker/render/view.h"

namespace lsqsurf::render {
namespace {

using core::Vec3d;

struct Sample {
  double value = std::numeric_limits<double>::quiet_NaN();
  Vec3d gradient = Vec3d::Zero();
};

// Trilinear value and gradient at x; NaN where x is outside the grid or a corner is outside
// the data.
Sample At(const VolumeGrid& g, const Vec3d& x) {
  Sample s;
  std::array<int, 3> i0;
  Vec3d f;
  for (int a = 0; a < 3; ++a) {
    const double t = (x[a] - g.origin[a]) / g.spacing[a];
    if (!(t >= 0 && t <= g.dims[a] - 1)) return s;
    i0[a] = std::min(static_cast<int>(t), g.dims[a] - 2);
    f[a] = t - i0[a];
  }
  double v = 0;
  Vec3d grad = Vec3d::Zero();
  for (int c = 0; c < 8; ++c) {
    const int dx = c & 1, dy = (c >> 1) & 1, dz = (c >> 2) & 1;
    const size_t k = (static_cast<size_t>(i0[2] + dz) * g.dims[1] + (i0[1] + dy)) * g.dims[0] + (i0[0] + dx);
    const double w = (dx ? f[0] : 1 - f[0]) * (dy ? f[1] : 1 - f[1]) * (dz ? f[2] : 1 - f[2]);
    v += w * g.values[k];
    grad += w * g.gradients[k].cast<double>();
  }
  s.value = v;  // NaN when any corner is NaN.
  s.gradient = grad;
  return s;
}

double Opacity(const std::vector<std::array<double, 2>>& points, double t) {
  if (t <= points.front()[0]) return points.front()[1];
  for (size_t k = 1; k < points.size(); ++k) {
    if (t <= points[k][0]) {
      const double u = (t - points[k - 1][0]) / std::max(points[k][0] - points[k - 1][0], 1e-12);
      return points[k - 1][1] + u * (points[k][1] - points[k - 1][1]);
    }
  }
  return points.back()[1];
}

// Headlight shading of a surface-like sample: the light comes with the ray.
double Diffuse(const Vec3d& gradient, const Vec3d& dir) {
  const double n = gradient.norm();
  return n > 0 ? std::abs(gradient.dot(dir)) / n : 1.0;
}

}  // namespace

namespace internal {

std::pair<double, double> VolumeColorRange(const VolumeGrid& grid, const RenderParams& p) {
  if (p.color_min != p.color_max) return {p.color_min, p.color_max};
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (float v : grid.values) {
    if (std::isfinite(v)) lo = std::min<double>(lo, v), hi = std::max<double>(hi, v);
  }
  return lo <= hi ? std::pair{lo, hi} : std::pair{0.0, 0.0};
}

}  // namespace internal

double GridValue(const VolumeGrid& grid, const core::Vec3d& x) { return At(grid, x).value; }

absl::StatusOr<std::vector<std::array<double, 2>>> ParseOpacity(std::string_view text) {
  std::vector<std::array<double, 2>> out;
  size_t pos = 0;
  while (pos < text.size()) {
    size_t end = text.find(',', pos);
    if (end == std::string_view::npos) end = text.size();
    const std::string_view item = text.substr(pos, end - pos);
    const size_t colon = item.find(':');
    std::array<double, 2> p{};
    bool ok = colon != std::string_view::npos;
    for (int k = 0; ok && k < 2; ++k) {
      const std::string_view part = k == 0 ? item.substr(0, colon) : item.substr(colon + 1);
      auto [q, ec] = std::from_chars(part.data(), part.data() + part.size(), p[k]);
      ok = ec == std::errc() && q == part.data() + part.size() && p[k] >= 0 && p[k] <= 1;
    }
    if (!ok || (!out.empty() && p[0] < out.back()[0])) {
      return absl::InvalidArgumentError(core::StrCat(
          "opacity: '", item, "' is not t:alpha with both in [0, 1] and t increasing (e.g. 0:0,0.5:0.05,1:0.4)"));
    }
    out.push_back(p);
    pos = end + 1;
  }
  if (out.empty()) return absl::InvalidArgumentError("opacity: give at least one t:alpha point");
  return out;
}

absl::StatusOr<Image> RaycastVolume(const VolumeGrid& g, const RenderParams& p, RenderInfo* info) {
  LSQSURF_RETURN_IF_ERROR(Validate(p));
  const size_t count = static_cast<size_t>(g.dims[0]) * g.dims[1] * g.dims[2];
  if (g.dims[0] < 2 || g.dims[1] < 2 || g.dims[2] < 2 || g.values.size() != count || g.gradients.size() != count) {
    return absl::InvalidArgumentError("the volume grid is empty or its arrays do not match its size");
  }
  LSQSURF_ASSIGN_OR_RETURN(auto opacity, ParseOpacity(p.opacity));
  const core::Box3 box(g.origin,
                       g.origin + (Vec3d(g.dims[0], g.dims[1], g.dims[2]) - Vec3d::Ones()).cwiseProduct(g.spacing));
  // Plain names, not a structured binding: the lambdas below capture them (clang before 16
  // cannot capture bindings).
  const std::pair<double, double> range = internal::VolumeColorRange(g, p);
  const double lo = range.first, hi = range.second;
  const double span = hi > lo ? hi - lo : 1.0;
  const internal::View view = internal::MakeView(box, p);
  const Eigen::Matrix4d inverse = (view.projection.cast<double>() * view.model_view.cast<double>()).inverse();
  const double cell = g.spacing.minCoeff();
  const double step = p.ray_step * cell;
  const double step_cells = p.ray_step;
  Image image;
  image.width = p.width;
  image.height = p.height;
  image.rgba.resize(4 * static_cast<size_t>(p.width) * static_cast<size_t>(p.height));
  const std::array<float, 3> bg = p.background;
  auto shade = [&](size_t px, size_t py) {
    const double nx = (static_cast<double>(px) + 0.5) / p.width * 2 - 1;
    const double ny = 1 - (static_cast<double>(py) + 0.5) / p.height * 2;
    const Eigen::Vector4d a = inverse * Eigen::Vector4d(nx, ny, -1, 1), b = inverse * Eigen::Vector4d(nx, ny, 1, 1);
    const Vec3d from = a.head<3>() / a[3], to = b.head<3>() / b[3];
    const Vec3d dir = (to - from).normalized();
    // The ray's stretch inside the box (slabs).
    double t0 = 0, t1 = 1e300;
    for (int k = 0; k < 3; ++k) {
      const double inv = 1.0 / dir[k];
      double u0 = (box.min()[k] - from[k]) * inv, u1 = (box.max()[k] - from[k]) * inv;
      if (u0 > u1) std::swap(u0, u1);
      t0 = std::max(t0, u0);
      t1 = std::min(t1, u1);
    }
    Vec3d color = Vec3d::Zero();
    double alpha = 0;
    Sample previous;
    for (double t = t0; t <= t1 && alpha < 0.995; t += step) {
      const Vec3d x = from + t * dir;
      const Sample s = At(g, x);
      if (p.volume_mode == VolumeMode::kIsosurface) {
        if (std::isfinite(s.value) && std::isfinite(previous.value) &&
            (s.value >= p.iso_value) != (previous.value >= p.iso_value)) {
          // Bisection between the two samples for the crossing.
          double ta = t - step, tb = t;
          double fa = previous.value - p.iso_value;
          Sample hit = s;
          for (int it = 0; it < 8; ++it) {
            const double tm = 0.5 * (ta + tb);
            const Sample m = At(g, from + tm * dir);
            if (!std::isfinite(m.value)) break;
            hit = m;
            if ((m.value - p.iso_value < 0) == (fa < 0)) {
              ta = tm;
              fa = m.value - p.iso_value;
            } else {
              tb = tm;
            }
          }
          const double d = Diffuse(hit.gradient, dir);
          const Vec3d base(p.base_color[0], p.base_color[1], p.base_color[2]);
          color = base * (0.18 + 0.82 * d) + Vec3d::Constant(p.specular * std::pow(d, 48.0));
          alpha = 1;
          break;
        }
        previous = s;
        continue;
      }
      if (!std::isfinite(s.value)) continue;
      const double u = std::clamp((s.value - lo) / span, 0.0, 1.0);
      const double a_cell = Opacity(opacity, u);
      if (a_cell <= 0) continue;
      const double a_step = 1 - std::pow(1 - std::min(a_cell, 0.999999), step_cells);
      const std::array<float, 3> c = ColorMap(u);
      const double light = 0.35 + 0.65 * Diffuse(s.gradient, dir);
      color += (1 - alpha) * a_step * light * Vec3d(c[0], c[1], c[2]);
      alpha += (1 - alpha) * a_step;
    }
    const double back = p.transparent ? 0.0 : 1.0;
    uint8_t* out = &image.rgba[4 * (py * static_cast<size_t>(p.width) + px)];
    for (int k = 0; k < 3; ++k) {
      const double v = color[k] + (1 - alpha) * back * bg[k];
      out[k] = static_cast<uint8_t>(std::lround(255 * std::clamp(v, 0.0, 1.0)));
    }
    out[3] = static_cast<uint8_t>(std::lround(255 * (p.transparent ? alpha : 1.0)));
  };
  (void)core::ParallelFor(static_cast<size_t>(p.height), 4, [&](size_t begin, size_t end) {
    for (size_t py = begin; py < end; ++py) {
      for (size_t px = 0; px < static_cast<size_t>(p.width); ++px) shade(px, py);
    }
  });
  if (info != nullptr) {
    info->color_min = lo;
    info->color_max = hi;
    info->renderer = core::StrCat("CPU ray caster (", core::ParallelismLevel(), " threads)");
  }
  return image;
}

}  // namespace lsqsurf::render
