// Backend-independent parts of worker/render: parameter checks, the colour map, PNG output.
#include <algorithm>
#include <cmath>

#include "stb_image_write.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/render/render.h"

namespace lsqsurf::render {

namespace {

// Camera fields live one level down; the table reaches them through these accessors.
core::ParamInfo CameraReal(std::string name, double lo, double hi, std::string help) {
  return {.name = std::move(name),
          .type = core::ParamType::kReal,
          .min_value = lo,
          .max_value = hi,
          .unit = "degrees",
          .help = std::move(help)};
}

}  // namespace

const core::ParamTable<RenderParams>& ViewParamTable() {
  static const auto* table = [] {
    auto* t = new core::ParamTable<RenderParams>();
    t->Integer<&RenderParams::width>("width", 16, kMaxImageSide, "pixels", "image width")
        .Integer<&RenderParams::height>("height", 16, kMaxImageSide, "pixels", "image height")
        .Custom(
            CameraReal("azimuth_deg", -1e6, 1e6, "camera angle about the up axis"),
            [](const RenderParams& p) { return p.camera.azimuth_deg; },
            [](RenderParams& p, double v) { p.camera.azimuth_deg = v; })
        .Custom(
            CameraReal("elevation_deg", -89, 89, "camera angle above the plane normal to the up axis"),
            [](const RenderParams& p) { return p.camera.elevation_deg; },
            [](RenderParams& p, double v) { p.camera.elevation_deg = v; })
        .Custom(
            {.name = "distance",
             .type = core::ParamType::kReal,
             .max_value = 1e30,
             .unit = "model units",
             .help = "camera distance from the centre of the box; 0 frames the whole model"},
            [](const RenderParams& p) { return p.camera.distance; },
            [](RenderParams& p, double v) { p.camera.distance = v; })
        .Custom(
            CameraReal("fov_deg", 5, 120, "vertical field of view"),
            [](const RenderParams& p) { return p.camera.fov_deg; },
            [](RenderParams& p, double v) { p.camera.fov_deg = v; })
        .Custom(
            {.name = "up_axis",
             .type = core::ParamType::kChoice,
             .help = "the axis that points up in the picture",
             .choices = {{"x", static_cast<int>(UpAxis::kX), "azimuth turns from +y towards +z"},
                         {"y", static_cast<int>(UpAxis::kY), "azimuth turns from +z towards +x (most scans)"},
                         {"z", static_cast<int>(UpAxis::kZ), "azimuth turns from +x towards +y"}}},
            [](const RenderParams& p) { return static_cast<double>(static_cast<int>(p.camera.up)); },
            [](RenderParams& p, double v) { p.camera.up = static_cast<UpAxis>(static_cast<int>(v)); })
        .Text<&RenderParams::color_attribute>("color",
                                              "per-vertex scalar to colour by, with a legend; rgb = the vertices' "
                                              "own colour (red, green, blue); empty = plain shading")
        .Real<&RenderParams::color_min>("color_min", -1e300, 1e300, "",
                                        "colour map bounds; the data's range unless color_min < color_max")
        .Real<&RenderParams::color_max>("color_max", -1e300, 1e300, "", "see color_min")
        .Custom(
            {.name = "flat_shading", .type = core::ParamType::kFlag, .max_value = 1, .help = "one normal per triangle"},
            [](const RenderParams& p) { return p.shading == Shading::kFlat ? 1.0 : 0.0; },
            [](RenderParams& p, double v) { p.shading = v != 0 ? Shading::kFlat : Shading::kSmooth; })
        .Flag<&RenderParams::wireframe>("wireframe", "dark triangle edges over the faces")
        .Flag<&RenderParams::transparent>("transparent", "transparent background")
        .Integer<&RenderParams::samples>("samples", 1, 8, "per pixel", "multisampling: 1, 2, 4 or 8")
        .Choice<&RenderParams::volume_mode>(
            "volume_mode",
            {{"direct", static_cast<int>(VolumeMode::kDirect), "front-to-back compositing through the opacity"},
             {"isosurface", static_cast<int>(VolumeMode::kIsosurface), "the first crossing of iso_value, shaded"}},
            "volume fields: how the field is drawn")
        .Text<&RenderParams::opacity>("opacity",
                                      "volume fields: t:alpha points, t in [0, 1] over the colour range, alpha the "
                                      "opacity one grid cell gathers")
        .Real<&RenderParams::iso_value>("iso_value", -1e30, 1e30, "field units",
                                        "volume fields: the level drawn "
                                        "in isosurface mode")
        .Integer<&RenderParams::volume_resolution>("volume_resolution", 16, 512, "grid points",
                                                   "volume fields: samples along the longest side of the box")
        .Real<&RenderParams::ray_step>("ray_step", 0.1, 2, "grid cells", "volume fields: ray-marching step")
        .AddRule([](const RenderParams& p) { return ParseOpacity(p.opacity).status(); })
        .AddRule([](const RenderParams& p) {
          return p.samples == 1 || p.samples == 2 || p.samples == 4 || p.samples == 8
                     ? absl::OkStatus()
                     : absl::InvalidArgumentError(core::StrCat("samples=", p.samples, " must be 1, 2, 4 or 8"));
        })
        .AddRule([](const RenderParams& p) {
          return p.color_min <= p.color_max ? absl::OkStatus()
                                            : absl::InvalidArgumentError("color_min must not exceed color_max");
        });
    return t;
  }();
  return *table;
}

absl::Status Validate(const RenderParams& p) {
  LSQSURF_RETURN_IF_ERROR(ViewParamTable().Validate(p));
  const Camera& c = p.camera;
  if (!std::isfinite(c.azimuth_deg) || !(std::abs(c.elevation_deg) <= 89) || !(c.fov_deg >= 5 && c.fov_deg <= 120) ||
      !(c.distance >= 0) || !std::isfinite(c.distance)) {
    return absl::InvalidArgumentError("camera: elevation must be in [-89, 89], fov in [5, 120] degrees, distance >= 0");
  }
  if (!c.framing_box.isEmpty() && !(c.framing_box.min().allFinite() && c.framing_box.max().allFinite())) {
    return absl::InvalidArgumentError("the framing box must have finite corners");
  }
  if (!(p.specular >= 0 && p.specular <= 1)) return absl::InvalidArgumentError("specular must be in [0, 1]");
  if (!std::isfinite(p.color_min) || !std::isfinite(p.color_max) || p.color_min > p.color_max) {
    return absl::InvalidArgumentError("the colour range needs finite bounds with min <= max");
  }
  if (!(p.point_size >= 0 && p.point_size <= 64))
    return absl::InvalidArgumentError("point_size must be in [0, 64] pixels");
  for (float v : p.background) {
    if (!(v >= 0 && v <= 1)) return absl::InvalidArgumentError("background components must be in [0, 1]");
  }
  return absl::OkStatus();
}

absl::StatusOr<UpAxis> ParseUpAxis(std::string_view name) {
  if (!name.empty() && name.front() == '+') name.remove_prefix(1);
  if (name == "x") return UpAxis::kX;
  if (name == "y") return UpAxis::kY;
  if (name == "z") return UpAxis::kZ;
  return absl::InvalidArgumentError(core::StrCat("unknown up axis '", name, "' (use x, y or z)"));
}

std::array<float, 3> ColorMap(double t) {
  // Anchors of a perceptually ordered blue–green–yellow ramp; linear in between.
  static constexpr std::array<std::array<float, 3>, 5> kAnchors = {{{0.267f, 0.005f, 0.329f},
                                                                    {0.229f, 0.322f, 0.546f},
                                                                    {0.128f, 0.567f, 0.551f},
                                                                    {0.369f, 0.789f, 0.383f},
                                                                    {0.993f, 0.906f, 0.144f}}};
  const double s = std::clamp(std::isfinite(t) ? t : 0.0, 0.0, 1.0) * (kAnchors.size() - 1);
  const auto i = std::min(static_cast<size_t>(s), kAnchors.size() - 2);
  const auto f = static_cast<float>(s - static_cast<double>(i));
  std::array<float, 3> rgb{};
  for (size_t c = 0; c < 3; ++c) rgb[c] = kAnchors[i][c] + f * (kAnchors[i + 1][c] - kAnchors[i][c]);
  return rgb;
}

absl::StatusOr<std::string> EncodePng(const Image& image) {
  if (image.width <= 0 || image.height <= 0 ||
      image.rgba.size() != 4 * static_cast<size_t>(image.width) * static_cast<size_t>(image.height)) {
    return absl::InvalidArgumentError("cannot encode an empty or inconsistent image");
  }
  std::string png;
  auto append = [](void* context, void* data, int size) {
    static_cast<std::string*>(context)->append(static_cast<const char*>(data), static_cast<size_t>(size));
  };
  if (stbi_write_png_to_func(append, &png, image.width, image.height, 4, image.rgba.data(), 4 * image.width) == 0) {
    return absl::InternalError("PNG encoding failed");
  }
  return png;
}

absl::StatusOr<Renderer*> SharedRenderer::Get() {
  std::lock_guard lock(mutex_);
  if (!renderer_) {
    auto created = CreateRenderer(backend_);
    if (!created.ok()) return created.status();
    renderer_ = *std::move(created);
  }
  return renderer_.get();
}

}  // namespace lsqsurf::render
