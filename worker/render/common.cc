// Backend-independent parts of worker/render: parameter checks, the colour map, PNG output.
#include <algorithm>
#include <cmath>

#include "stb_image_write.h"
#include "worker/core/strings.h"
#include "worker/render/render.h"

namespace lsqsurf::render {

absl::Status Validate(const RenderParams& p) {
  auto side_ok = [](int s) { return s >= 16 && s <= kMaxImageSide; };
  if (!side_ok(p.width) || !side_ok(p.height)) {
    return absl::InvalidArgumentError(core::StrCat("image size ", p.width, "x", p.height, " is outside 16..",
                                                   kMaxImageSide, " pixels per side"));
  }
  if (p.samples != 1 && p.samples != 2 && p.samples != 4 && p.samples != 8) {
    return absl::InvalidArgumentError("samples must be 1, 2, 4 or 8");
  }
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
  if (!(p.point_size >= 0 && p.point_size <= 64)) return absl::InvalidArgumentError("point_size must be in [0, 64] pixels");
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

}  // namespace lsqsurf::render
