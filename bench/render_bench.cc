// lsqsurf-render-bench — milliseconds per frame of the headless renderer: a sphere tessellated
// to about --triangles triangles, drawn at --size² with the default shading (smooth, specular,
// 4× MSAA) or the options given, first frame and steady state (median of --frames).
#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <vector>

#include "worker/core/sphere_mesh.h"
#include "worker/render/render.h"

namespace {

// A latitude–longitude sphere with about `triangles` faces.
lsqsurf::core::TriangleMesh Sphere(double triangles) {
  const int rings = std::max(4, static_cast<int>(std::sqrt(triangles / 4)));
  return lsqsurf::core::SphereMesh(rings, 2 * rings);
}

}  // namespace

int main(int argc, char** argv) {
  using namespace lsqsurf;
  CLI::App app{"lsqsurf-render-bench: milliseconds per frame of the headless renderer"};
  std::vector<double> sizes_in_triangles = {1e5, 1e6};
  int size = 1024, frames = 7, samples = 4;
  bool wireframe = false, flat = false, colour = false;
  app.add_option("--triangles", sizes_in_triangles, "mesh sizes in triangles (repeatable)")->capture_default_str();
  app.add_option("--size", size, "image side in pixels")->capture_default_str();
  app.add_option("--frames", frames, "frames per case; the steady figure is their median")->capture_default_str();
  app.add_option("--samples", samples, "MSAA samples per pixel")->capture_default_str();
  app.add_flag("--wireframe", wireframe, "draw the edges too");
  app.add_flag("--flat", flat, "flat shading");
  app.add_flag("--color", colour, "colour by the height attribute, with the legend");
  CLI11_PARSE(app, argc, argv);

  auto renderer = render::CreateRenderer("auto");
  if (!renderer.ok()) return std::fprintf(stderr, "%s\n", renderer.status().ToString().c_str()), 1;
  std::printf("renderer: %s\n", (*renderer)->description().c_str());
  std::printf("%12s %6s %8s %12s %12s\n", "triangles", "size", "samples", "first_ms", "steady_ms");
  render::RenderParams p;
  p.width = p.height = size;
  p.samples = samples;
  p.wireframe = wireframe;
  p.shading = flat ? render::Shading::kFlat : render::Shading::kSmooth;
  if (colour) p.color_attribute = "height";
  for (double n : sizes_in_triangles) {
    const core::TriangleMesh mesh = Sphere(n);
    std::vector<double> ms;
    for (int f = 0; f < std::max(2, frames); ++f) {
      const auto start = std::chrono::steady_clock::now();
      auto image = (*renderer)->RenderMesh(mesh, p);
      if (!image.ok()) return std::fprintf(stderr, "%s\n", image.status().ToString().c_str()), 1;
      ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
    }
    const double first = ms.front();
    std::vector<double> steady(ms.begin() + 1, ms.end());
    std::nth_element(steady.begin(), steady.begin() + static_cast<std::ptrdiff_t>(steady.size() / 2), steady.end());
    std::printf("%12zu %6d %8d %12.1f %12.1f\n", mesh.faces.size(), size, samples, first, steady[steady.size() / 2]);
  }
  return 0;
}
