// worker/render/egl_shaders.h — the GLSL programs of the EGL renderer: the surface (meshes and
// points), the overlay (the colour legend) and the volume ray caster. Included by the EGL
// renderer's files only.
#pragma once

namespace lsqsurf::render::internal {

inline constexpr char kSurfaceVertex[] = R"(#version 450 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in float scalar;
uniform mat4 model_view;
uniform mat4 projection;
uniform vec2 scalar_map;   // (min, 1 / (max - min))
uniform float point_size;
uniform int packed_rgb;    // The scalar is a colour, r·65536 + g·256 + b.
out vec3 view_position;
out vec3 view_normal;
out float color_t;
out vec3 vertex_rgb;
void main() {
  vec4 p = model_view * vec4(position, 1.0);
  view_position = p.xyz;
  view_normal = mat3(model_view) * normal;
  color_t = (scalar - scalar_map.x) * scalar_map.y;
  // Unpacked in integers, exactly, before the channels are interpolated apart.
  uint bits = uint(max(scalar, 0.0) + 0.5);
  vertex_rgb = packed_rgb != 0 ? vec3((bits >> 16) & 255u, (bits >> 8) & 255u, bits & 255u) / 255.0 : vec3(0.0);
  gl_PointSize = point_size;
  gl_Position = projection * p;
}
)";

// mode 0: shaded surface; 1: wireframe lines; 2: point splats (round, shaded by their normal,
// or as small spheres when the cloud has none).
inline constexpr char kSurfaceFragment[] = R"(#version 450 core
in vec3 view_position;
in vec3 view_normal;
in float color_t;
in vec3 vertex_rgb;
uniform int mode;
uniform int flat_shading;
uniform int has_normals;
uniform int use_colormap;
uniform int packed_rgb;
uniform vec3 base_color;
uniform vec3 light_dir;
uniform float specular;
uniform sampler2D colormap;
out vec4 fragment;
void main() {
  if (mode == 1) { fragment = vec4(0.08, 0.08, 0.10, 1.0); return; }
  vec3 n;
  if (mode == 2) {
    vec2 c = 2.0 * gl_PointCoord - 1.0;
    float r2 = dot(c, c);
    if (r2 > 1.0) discard;
    n = has_normals != 0 ? normalize(view_normal) : vec3(c.x, -c.y, sqrt(1.0 - r2));
  } else if (flat_shading != 0 || has_normals == 0) {
    n = normalize(cross(dFdx(view_position), dFdy(view_position)));
  } else {
    n = normalize(view_normal);
  }
  vec3 v = normalize(-view_position);
  if (dot(n, v) < 0.0) n = -n;  // Two-sided: open surfaces show their back faces lit too.
  vec3 albedo = packed_rgb != 0   ? vertex_rgb
               : use_colormap != 0 ? texture(colormap, vec2(clamp(color_t, 0.0, 1.0), 0.5)).rgb
                                   : base_color;
  float diffuse = max(dot(n, light_dir), 0.0);
  float highlight = specular * pow(max(dot(n, normalize(light_dir + v)), 0.0), 48.0);
  fragment = vec4(albedo * (0.18 + 0.82 * diffuse) + vec3(highlight), 1.0);
}
)";

// Screen-space overlay (legend bar and labels): positions in pixels, t < 0 = label colour.
inline constexpr char kOverlayVertex[] = R"(#version 450 core
layout(location = 0) in vec2 pixel;
layout(location = 2) in float t;
uniform vec2 viewport;
out float color_t;
void main() {
  color_t = t;
  gl_Position = vec4(2.0 * pixel.x / viewport.x - 1.0, 1.0 - 2.0 * pixel.y / viewport.y, 0.0, 1.0);
}
)";

inline constexpr char kOverlayFragment[] = R"(#version 450 core
in float color_t;
uniform sampler2D colormap;
out vec4 fragment;
void main() {
  fragment = color_t < 0.0 ? vec4(0.05, 0.05, 0.05, 1.0) : vec4(texture(colormap, vec2(color_t, 0.5)).rgb, 1.0);
}
)";

constexpr int kColorMapTexels = 256;
inline constexpr int kMaxOpacityPoints = 16;

// Volume ray casting: one full-screen triangle; each fragment marches its ray through a 3-D
// texture of (value, gradient) exactly as RaycastVolume does on the CPU (render.h).
inline constexpr char kVolumeVertex[] = R"(#version 450 core
void main() {
  vec2 corner = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);
}
)";

inline constexpr char kVolumeFragment[] = R"(#version 450 core
uniform sampler3D field;
uniform sampler2D colormap;
uniform mat4 inverse_view_projection;
uniform vec2 viewport;
uniform vec3 box_min, box_max, dims;
uniform float step, step_cells, lo, span, iso, specular, back_alpha;
uniform int mode, opacity_count;
uniform float opacity_t[16], opacity_a[16];
uniform vec3 background, base_color;
out vec4 fragment;

bool finite(float v) { return !isnan(v) && !isinf(v); }
// The sample at x, and whether there is data there: inside the box and not NaN (missing data).
// No NaN is made here: GLSL leaves 0.0 / 0.0 undefined, and NVIDIA's compiler folds it to a number.
bool sample_at(vec3 x, out vec4 s) {
  vec3 t = (x - box_min) / (box_max - box_min);
  if (any(lessThan(t, vec3(0.0))) || any(greaterThan(t, vec3(1.0)))) {
    s = vec4(0.0);
    return false;
  }
  s = texture(field, (t * (dims - 1.0) + 0.5) / dims);
  return finite(s.x);
}
float opacity(float t) {
  if (t <= opacity_t[0]) return opacity_a[0];
  for (int k = 1; k < opacity_count; ++k) {
    if (t <= opacity_t[k]) {
      float u = (t - opacity_t[k - 1]) / max(opacity_t[k] - opacity_t[k - 1], 1e-12);
      return mix(opacity_a[k - 1], opacity_a[k], u);
    }
  }
  return opacity_a[opacity_count - 1];
}
float diffuse(vec3 g, vec3 dir) { float n = length(g); return n > 0.0 ? abs(dot(g, dir)) / n : 1.0; }

void main() {
  vec2 ndc = gl_FragCoord.xy / viewport * 2.0 - 1.0;
  vec4 a = inverse_view_projection * vec4(ndc, -1.0, 1.0), b = inverse_view_projection * vec4(ndc, 1.0, 1.0);
  vec3 from = a.xyz / a.w, dir = normalize(b.xyz / b.w - from);
  vec3 u0 = (box_min - from) / dir, u1 = (box_max - from) / dir;
  vec3 near = min(u0, u1), far = max(u0, u1);
  float t0 = max(max(max(near.x, near.y), near.z), 0.0), t1 = min(min(far.x, far.y), far.z);
  vec3 color = vec3(0.0);
  float alpha = 0.0;
  vec4 previous = vec4(0.0);
  bool had_data = false;  // Whether `previous` holds data.
  for (float t = t0; t <= t1 && alpha < 0.995; t += step) {
    vec4 s;
    bool has_data = sample_at(from + t * dir, s);
    if (mode == 1) {
      if (has_data && had_data && ((s.x >= iso) != (previous.x >= iso))) {
        float ta = t - step, tb = t, fa = previous.x - iso;
        vec4 hit = s;
        for (int it = 0; it < 8; ++it) {
          float tm = 0.5 * (ta + tb);
          vec4 m;
          if (!sample_at(from + tm * dir, m)) break;
          hit = m;
          if ((m.x - iso < 0.0) == (fa < 0.0)) { ta = tm; fa = m.x - iso; } else { tb = tm; }
        }
        float d = diffuse(hit.yzw, dir);
        color = base_color * (0.18 + 0.82 * d) + vec3(specular * pow(d, 48.0));
        alpha = 1.0;
        break;
      }
      previous = s;
      had_data = has_data;
      continue;
    }
    if (!has_data) continue;
    float u = clamp((s.x - lo) / span, 0.0, 1.0);
    float a_cell = opacity(u);
    if (a_cell <= 0.0) continue;
    float a_step = 1.0 - pow(1.0 - min(a_cell, 0.999999), step_cells);
    vec3 c = texture(colormap, vec2(u * (255.0 / 256.0) + 0.5 / 256.0, 0.5)).rgb;
    float light = 0.35 + 0.65 * diffuse(s.yzw, dir);
    color += (1.0 - alpha) * a_step * light * c;
    alpha += (1.0 - alpha) * a_step;
  }
  fragment = vec4(color + (1.0 - alpha) * back_alpha * background, back_alpha > 0.0 ? 1.0 : alpha);
}
)";

}  // namespace lsqsurf::render::internal
