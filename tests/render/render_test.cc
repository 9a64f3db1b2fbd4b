#include "worker/render/render.h"

#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <numbers>
#include <thread>

#include "stb_image.h"
#include "tests/test_shapes.h"

namespace lsqsurf::render {
namespace {

using core::Vec3d;

constexpr double kDegree = std::numbers::pi / 180;

class RenderTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    auto r = CreateRenderer("auto");
    ASSERT_TRUE(r.ok()) << r.status();
    renderer_ = r->release();
    std::printf("renderer: %s\n", renderer_->description().c_str());
  }
  static void TearDownTestSuite() {
    delete renderer_;
    renderer_ = nullptr;
  }
  // Unit sphere seen from distance 5 along +x (elevation 0), 30° field of view.
  static RenderParams SphereView(int size) {
    RenderParams p;
    p.width = p.height = size;
    p.camera.azimuth_deg = 0;
    p.camera.elevation_deg = 0;
    p.camera.distance = 5;
    p.camera.fov_deg = 30;
    return p;
  }
  // The sphere's silhouette radius in pixels: the tangent cone's half-angle asin(r/d), projected.
  static double SilhouetteRadius(const RenderParams& p) {
    return std::tan(std::asin(1.0 / p.camera.distance)) / std::tan(0.5 * p.camera.fov_deg * kDegree) * 0.5 * p.height;
  }
  static Renderer* renderer_;
};
Renderer* RenderTest::renderer_ = nullptr;

int Brightness(const Image& image, int x, int y) {
  const auto c = image.At(x, y);
  return c[0] + c[1] + c[2];
}

TEST_F(RenderTest, SilhouetteMatchesTheProjectedSphere) {
  RenderParams p = SphereView(512);
  p.samples = 1;  // Whole pixels, so that covered pixels can be counted.
  p.transparent = true;
  const core::TriangleMesh sphere = core::SphereMesh(128, 256);
  auto image = renderer_->RenderMesh(sphere, p);
  ASSERT_TRUE(image.ok()) << image.status();
  double covered = 0, cx = 0, cy = 0;
  for (int y = 0; y < p.height; ++y) {
    for (int x = 0; x < p.width; ++x) {
      if (image->At(x, y)[3] < 128) continue;
      covered += 1;
      cx += x + 0.5;
      cy += y + 0.5;
    }
  }
  const double radius = std::sqrt(covered / std::numbers::pi);
  EXPECT_NEAR(radius, SilhouetteRadius(p), 1.0);
  EXPECT_NEAR(cx / covered, 256, 0.5);
  EXPECT_NEAR(cy / covered, 256, 0.5);
  // Background, exactly, wherever the sphere is not: corners and just outside the silhouette.
  const int outside = static_cast<int>(256 + SilhouetteRadius(p) + 2);
  for (auto [x, y] : {std::pair{0, 0}, {511, 0}, {0, 511}, {511, 511}, {outside, 256}, {256, 511 - outside}}) {
    EXPECT_EQ(image->At(x, y)[3], 0) << x << "," << y;
  }
  // With the solid background every uncovered pixel is exactly the background colour.
  p.transparent = false;
  p.background = {0.2f, 0.4f, 0.6f};
  auto solid = renderer_->RenderMesh(sphere, p);
  ASSERT_TRUE(solid.ok());
  const auto corner = solid->At(3, 3);
  EXPECT_EQ(corner[0], 51);
  EXPECT_EQ(corner[1], 102);
  EXPECT_EQ(corner[2], 153);
  EXPECT_EQ(corner[3], 255);
}

TEST_F(RenderTest, ShadingFallsMonotonicallyAwayFromTheLight) {
  RenderParams p = SphereView(256);
  p.specular = 0;  // Lambert only: brightness = ambient + diffuse · max(0, n·l).
  auto image = renderer_->RenderMesh(core::SphereMesh(128, 256), p);
  ASSERT_TRUE(image.ok()) << image.status();
  // The light comes from up-left of the camera: along the diagonal from the top-left to the
  // bottom-right of the disc, brightness rises to one peak in the top-left half, then falls.
  const int r = static_cast<int>(SilhouetteRadius(p) * 0.98 / std::sqrt(2.0));
  std::vector<int> line;
  for (int k = -r; k <= r; ++k) line.push_back(Brightness(*image, 128 + k, 128 + k));
  const auto peak = std::max_element(line.begin(), line.end()) - line.begin();
  EXPECT_LT(peak, r) << "the brightest point should face the light (top left)";
  EXPECT_GT(peak, r / 4);
  for (size_t k = static_cast<size_t>(peak) + 1; k < line.size(); ++k) EXPECT_LE(line[k], line[k - 1] + 2) << k;
  for (size_t k = 1; k <= static_cast<size_t>(peak); ++k) EXPECT_GE(line[k], line[k - 1] - 2) << k;
  EXPECT_GT(line[static_cast<size_t>(peak)], 2 * line.back()) << "lit side much brighter than the far side";
}

TEST_F(RenderTest, ColouredAttributeFollowsTheLegend) {
  RenderParams p = SphereView(512);
  p.specular = 0;
  p.color_attribute = "height";
  RenderInfo info;
  auto image = renderer_->RenderMesh(core::SphereMesh(128, 256), p, &info);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_NEAR(info.color_min, -1, 1e-6);
  EXPECT_NEAR(info.color_max, 1, 1e-6);
  // The legend bar: top = maximum, bottom = minimum, the colour map in between.
  const int bar_x = p.width - 16;
  for (double t : {0.02, 0.3, 0.5, 0.7, 0.98}) {
    const int y = static_cast<int>(std::lround((0.85 - 0.7 * t) * p.height));
    const auto want = ColorMap(t);
    const auto got = image->At(bar_x, y);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(got[static_cast<size_t>(c)], 255 * want[static_cast<size_t>(c)], 6) << t;
  }
  // On the sphere, shading scales all channels alike: a pixel's chromaticity is that of the
  // colour map at its height. Heights come from intersecting the pixel's ray with the sphere.
  const double focal = 0.5 * p.height / std::tan(0.5 * p.camera.fov_deg * kDegree);
  for (int py : {150, 200, 256, 300, 350}) {
    const Vec3d eye(5, 0, 0);
    const Vec3d dir = Vec3d(-focal, 0, 256.0 - (py + 0.5)).normalized();  // Column 256: y = 0.
    const double b = eye.dot(dir), disc = b * b - (eye.squaredNorm() - 1);
    ASSERT_GT(disc, 0) << py;
    const double z = (eye + (-b - std::sqrt(disc)) * dir).z();
    const auto want = ColorMap(0.5 * (z + 1));
    const auto got = image->At(256, py);
    const double want_sum = want[0] + want[1] + want[2], got_sum = got[0] + got[1] + got[2];
    for (size_t c = 0; c < 3; ++c) {
      EXPECT_NEAR(got[c] / got_sum, want[c] / want_sum, 0.03) << "row " << py << " channel " << c;
    }
  }
}

// color=rgb draws the vertices' own colour: the upper half of the sphere orange, the lower
// blue, each pixel with its colour's chromaticity (shading scales the channels alike), no legend.
TEST_F(RenderTest, TrueColourDrawsTheVerticesOwnColour) {
  RenderParams p = SphereView(512);
  p.specular = 0;
  p.color_attribute = kTrueColour;
  core::TriangleMesh sphere = core::SphereMesh(128, 256);
  const float upper[3] = {230, 120, 20}, lower[3] = {20, 90, 240};
  for (int c = 0; c < 3; ++c) {
    core::ScalarAttribute channel{core::kColourChannels[c], {}};
    for (const core::Vec3f& v : sphere.vertices) channel.values.push_back(v.z() > 0 ? upper[c] : lower[c]);
    sphere.vertex_attributes.push_back(std::move(channel));
  }
  auto image = renderer_->RenderMesh(sphere, p);
  ASSERT_TRUE(image.ok()) << image.status();
  for (const auto& [py, want] : {std::pair{170, upper}, std::pair{340, lower}}) {
    const auto got = image->At(256, py);
    const double want_sum = want[0] + want[1] + want[2], got_sum = got[0] + got[1] + got[2];
    ASSERT_GT(got_sum, 60) << py;
    for (size_t c = 0; c < 3; ++c) EXPECT_NEAR(got[c] / got_sum, want[c] / want_sum, 0.03) << py << " " << c;
  }
  // No colour bar where a scalar would have one: the background.
  const auto bar = image->At(p.width - 16, p.height / 2);
  EXPECT_EQ(bar[0] + bar[1] + bar[2], 3 * 255);
  // Without the three channels it says so.
  EXPECT_EQ(renderer_->RenderMesh(core::SphereMesh(16, 32), p).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(RenderTest, CullingHiddenFacesLeavesThePictureUnchanged) {
  // The closed sphere is drawn with its back faces culled; the same sphere less one face on the
  // far side is open, so every face is drawn. Only silhouette samples may differ (there a back
  // face can cover a sample that no front face does).
  RenderParams p = SphereView(256);
  const core::TriangleMesh closed = core::SphereMesh(96, 192);
  core::TriangleMesh open = closed;
  const auto far_face = std::find_if(open.faces.begin(), open.faces.end(), [&](const core::Triangle& f) {
    return open.vertices[f[0]].x() < -0.99f && open.vertices[f[1]].x() < -0.99f && open.vertices[f[2]].x() < -0.99f;
  });
  ASSERT_NE(far_face, open.faces.end());
  open.faces.erase(far_face);
  for (bool reversed : {false, true}) {
    core::TriangleMesh a = closed, b = open;
    if (reversed) {
      for (auto* m : {&a, &b}) {
        for (core::Triangle& f : m->faces) std::swap(f[1], f[2]);
      }
    }
    auto culled = renderer_->RenderMesh(a, p);
    auto full = renderer_->RenderMesh(b, p);
    ASSERT_TRUE(culled.ok() && full.ok());
    const double r = SilhouetteRadius(p);
    int differing = 0, covered = 0;
    for (int y = 0; y < 256; ++y) {
      for (int x = 0; x < 256; ++x) {
        const double d = std::hypot(x + 0.5 - 128, y + 0.5 - 128);
        if (d < r) ++covered;
        if (culled->At(x, y) == full->At(x, y)) continue;
        ++differing;
        EXPECT_GT(d, r - 2) << "a visible pixel changed at " << x << "," << y << (reversed ? " (reversed)" : "");
      }
    }
    EXPECT_LT(differing, covered / 50) << (reversed ? "reversed" : "");
  }
}

// The mesh's faces in `count` runs, each run a mesh of its own with the vertices it uses.
class SplitMesh final : public MeshPieces {
 public:
  SplitMesh(const core::TriangleMesh& mesh, size_t count) : mesh_(mesh), count_(count) {}
  absl::Status ForEach(const std::function<absl::Status(const core::TriangleMesh&)>& visit) const override {
    const size_t per_piece = (mesh_.faces.size() + count_ - 1) / count_;
    for (size_t begin = 0; begin < mesh_.faces.size(); begin += per_piece) {
      core::TriangleMesh piece;
      piece.vertex_attributes = {{mesh_.vertex_attributes[0].name, {}}};
      std::vector<int64_t> local(mesh_.vertices.size(), -1);
      for (size_t f = begin; f < std::min(mesh_.faces.size(), begin + per_piece); ++f) {
        core::Triangle t;
        for (int k = 0; k < 3; ++k) {
          const uint32_t v = mesh_.faces[f][k];
          if (local[v] < 0) {
            local[v] = static_cast<int64_t>(piece.vertices.size());
            piece.vertices.push_back(mesh_.vertices[v]);
            piece.normals.push_back(mesh_.normals[v]);
            piece.vertex_attributes[0].values.push_back(mesh_.vertex_attributes[0].values[v]);
          }
          t[k] = static_cast<uint32_t>(local[v]);
        }
        piece.faces.push_back(t);
      }
      if (absl::Status s = visit(piece); !s.ok()) return s;
    }
    return absl::OkStatus();
  }

 private:
  const core::TriangleMesh& mesh_;
  size_t count_;
};

TEST_F(RenderTest, PiecesDrawTheirJoinedMesh) {
  RenderParams p = SphereView(256);
  p.samples = 1;
  p.color_attribute = "height";
  const core::TriangleMesh sphere = core::SphereMesh(96, 192);
  RenderInfo whole_info, pieces_info;
  auto whole = renderer_->RenderMesh(sphere, p, &whole_info);
  auto pieces = renderer_->RenderMeshPieces(SplitMesh(sphere, 7), p, &pieces_info);
  ASSERT_TRUE(whole.ok() && pieces.ok()) << whole.status() << pieces.status();
  // The joint range and box: the same colours, the same framing.
  EXPECT_EQ(pieces_info.color_min, whole_info.color_min);
  EXPECT_EQ(pieces_info.color_max, whole_info.color_max);
  // Only silhouette pixels may differ (the whole sphere is closed: its back faces are culled).
  const double r = SilhouetteRadius(p);
  int differing = 0, covered = 0;
  for (int y = 0; y < 256; ++y) {
    for (int x = 0; x < 256; ++x) {
      const double d = std::hypot(x + 0.5 - 128, y + 0.5 - 128);
      covered += d < r;
      if (whole->At(x, y) == pieces->At(x, y)) continue;
      ++differing;
      EXPECT_TRUE(d > r - 2 || x > 200) << "a visible pixel changed at " << x << "," << y;  // x > 200: the legend.
    }
  }
  EXPECT_LT(differing, covered / 50);

  // Nothing to draw, an attribute a piece lacks, a piece that fails: refused with the reason.
  core::TriangleMesh empty;
  empty.vertex_attributes = {{"height", {}}};
  EXPECT_EQ(renderer_->RenderMeshPieces(SplitMesh(empty, 1), p).status().code(), absl::StatusCode::kInvalidArgument);
  RenderParams other = p;
  other.color_attribute = "curvature";
  const auto lacking = renderer_->RenderMeshPieces(SplitMesh(sphere, 3), other).status();
  EXPECT_NE(lacking.message().find("no attribute 'curvature'"), std::string::npos) << lacking;
  class Failing final : public MeshPieces {
   public:
    absl::Status ForEach(const std::function<absl::Status(const core::TriangleMesh&)>&) const override {
      return absl::UnavailableError("the store went away");
    }
  };
  EXPECT_EQ(renderer_->RenderMeshPieces(Failing(), p).status().code(), absl::StatusCode::kUnavailable);
}

// Extent of the non-transparent pixels: (width, height, centre x, centre y).
std::array<double, 4> Coverage(const Image& image) {
  int x0 = image.width, x1 = -1, y0 = image.height, y1 = -1;
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x) {
      if (image.At(x, y)[3] < 128) continue;
      x0 = std::min(x0, x), x1 = std::max(x1, x), y0 = std::min(y0, y), y1 = std::max(y1, y);
    }
  }
  return {x1 - x0 + 1.0, y1 - y0 + 1.0, 0.5 * (x0 + x1 + 1), 0.5 * (y0 + y1 + 1)};
}

TEST_F(RenderTest, TheUpAxisPointsUpInThePicture) {
  // An ellipsoid twice as long along y as along x and z, seen from the side at distance 12.
  core::TriangleMesh ellipsoid = core::SphereMesh(48, 96);
  for (core::Vec3f& v : ellipsoid.vertices) v.y() *= 2;
  RenderParams p = SphereView(256);
  p.transparent = true;
  p.camera.distance = 12;
  const double focal = 128 / std::tan(0.5 * p.camera.fov_deg * kDegree);
  // A sphere of radius r at distance d spans 2·f·tan(asin(r/d)) pixels; the ellipsoid's long
  // axis lies across the view, where perspective stretches it slightly more.
  const double short_px = 2 * focal * std::tan(std::asin(1.0 / 12)), long_px = 2 * focal * 2 / std::sqrt(144 - 1.0);
  p.camera.up = UpAxis::kY;  // Azimuth 0, elevation 0: looking down −z, y up, x right.
  auto y_up = renderer_->RenderMesh(ellipsoid, p);
  ASSERT_TRUE(y_up.ok()) << y_up.status();
  const auto side = Coverage(*y_up);
  EXPECT_NEAR(side[0], short_px, 2);
  EXPECT_NEAR(side[1], long_px, 2);
  p.camera.up = UpAxis::kZ;  // Looking down −x, z up, y across.
  auto z_up = renderer_->RenderMesh(ellipsoid, p);
  ASSERT_TRUE(z_up.ok());
  const auto across = Coverage(*z_up);
  EXPECT_NEAR(across[0], long_px, 2);
  EXPECT_NEAR(across[1], short_px, 2);
  EXPECT_EQ(ParseUpAxis("+y").value(), UpAxis::kY);
  EXPECT_EQ(ParseUpAxis("w").status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(RenderTest, AFramingBoxMovesTheAimPoint) {
  // Aiming at (0, 0.5, 0) from +x at distance 10: the unit sphere at the origin lies 0.5 to the
  // left (screen right is +y). Its silhouette spans the angles atan(0.5/10) ± asin(1/|c|).
  RenderParams p = SphereView(256);
  p.transparent = true;
  p.camera.distance = 10;
  p.camera.framing_box = core::Box3(core::Vec3d(-1, -0.5, -1), core::Vec3d(1, 1.5, 1));
  auto image = renderer_->RenderMesh(core::SphereMesh(64, 128), p);
  ASSERT_TRUE(image.ok()) << image.status();
  const double focal = 128 / std::tan(0.5 * p.camera.fov_deg * kDegree);
  const double centre = std::atan(0.05), half = std::asin(1 / std::hypot(10.0, 0.5));
  const double left = 128 - focal * std::tan(centre + half), right = 128 - focal * std::tan(centre - half);
  const auto coverage = Coverage(*image);
  EXPECT_NEAR(coverage[0], right - left, 2);
  EXPECT_NEAR(coverage[2], 0.5 * (left + right), 1);
  EXPECT_NEAR(coverage[3], 128, 1);
  p.camera.framing_box = core::Box3(core::Vec3d(0, 0, 0), core::Vec3d(NAN, 1, 1));
  EXPECT_EQ(renderer_->RenderMesh(core::SphereMesh(8, 16), p).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(RenderTest, PointSplatsStayInsideTheSilhouette) {
  RenderParams p = SphereView(256);
  p.transparent = true;
  auto image = renderer_->RenderPoints(testing::SphereCloud(20000), p);
  ASSERT_TRUE(image.ok()) << image.status();
  const double radius = SilhouetteRadius(p);
  int inside = 0, drawn_inside = 0, drawn_far = 0;
  for (int y = 0; y < 256; ++y) {
    for (int x = 0; x < 256; ++x) {
      const double d = std::hypot(x + 0.5 - 128, y + 0.5 - 128);
      const bool drawn = image->At(x, y)[3] > 0;
      if (d < radius - 2) {
        ++inside;
        drawn_inside += drawn;
      } else if (d > radius + 6) {
        drawn_far += drawn;
      }
    }
  }
  EXPECT_GT(drawn_inside, 0.97 * inside) << "splats should close the surface";
  EXPECT_EQ(drawn_far, 0);
}

TEST_F(RenderTest, ConcurrentRequestsAllSucceedAndAgree) {
  const core::TriangleMesh sphere = core::SphereMesh(64, 128);
  RenderParams p = SphereView(200);
  p.wireframe = true;
  p.shading = Shading::kFlat;
  auto reference = renderer_->RenderMesh(sphere, p);
  ASSERT_TRUE(reference.ok()) << reference.status();
  std::vector<std::thread> threads;
  std::atomic<int> same{0}, failed{0};
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&] {
      for (int k = 0; k < 3; ++k) {
        auto image = renderer_->RenderMesh(sphere, p);
        if (!image.ok()) {
          ++failed;
        } else if (image->rgba == reference->rgba) {
          ++same;
        }
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(failed.load(), 0);
  EXPECT_EQ(same.load(), 12);
}

// Multisampling: one sample covers a pixel wholly or not at all, so the silhouette's alpha is
// 0 or 255; four (and eight, which a GL 4.5 context may cap at its own maximum, never below four)
// blend the edge pixels. Every documented value draws.
TEST_F(RenderTest, SamplesBlendTheSilhouetteAndEveryDocumentedCountDraws) {
  const core::TriangleMesh sphere = core::SphereMesh(32, 64);
  std::map<int, std::pair<Image, RenderInfo>> drawn;
  for (int samples : {1, 2, 4, 8}) {
    RenderParams p = SphereView(128);
    p.transparent = true;
    p.samples = samples;
    RenderInfo info;
    auto image = renderer_->RenderMesh(sphere, p, &info);
    ASSERT_TRUE(image.ok()) << samples << " samples: " << image.status();
    drawn[samples] = {*std::move(image), info};
  }
  auto partial = [](const Image& image) {
    int count = 0;
    for (int y = 0; y < image.height; ++y) {
      for (int x = 0; x < image.width; ++x) count += image.At(x, y)[3] > 0 && image.At(x, y)[3] < 255;
    }
    return count;
  };
  EXPECT_EQ(drawn[1].second.samples, 1);
  EXPECT_EQ(partial(drawn[1].first), 0);
  EXPECT_EQ(drawn[4].second.samples, 4);
  // The silhouette of a circle of radius ~29 px crosses about 2 pi r pixels.
  EXPECT_GT(partial(drawn[4].first), 100);
  EXPECT_NE(drawn[1].first.rgba, drawn[4].first.rgba);
  EXPECT_GE(drawn[8].second.samples, 4);
  EXPECT_LE(drawn[8].second.samples, 8);
  EXPECT_GT(partial(drawn[8].first), 100);
  EXPECT_GE(drawn[2].second.samples, 2);
}

TEST_F(RenderTest, BadRequestsAreRefused) {
  const core::TriangleMesh sphere = core::SphereMesh(8, 16);
  RenderParams p = SphereView(64);
  p.width = 5000;
  EXPECT_EQ(renderer_->RenderMesh(sphere, p).status().code(), absl::StatusCode::kInvalidArgument);
  p = SphereView(64);
  p.samples = 3;
  EXPECT_EQ(renderer_->RenderMesh(sphere, p).status().code(), absl::StatusCode::kInvalidArgument);
  p = SphereView(64);
  p.color_attribute = "degree";
  auto unknown = renderer_->RenderMesh(sphere, p);
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(unknown.status().message().find("height"), std::string_view::npos) << unknown.status();
  EXPECT_EQ(renderer_->RenderMesh(core::TriangleMesh{}, SphereView(64)).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(CreateRenderer("vulkan").status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(RenderTest, PngDecodesToTheSamePixels) {
  auto image = renderer_->RenderMesh(core::SphereMesh(16, 32), SphereView(64));
  ASSERT_TRUE(image.ok());
  auto png = EncodePng(*image);
  ASSERT_TRUE(png.ok()) << png.status();
  int w = 0, h = 0, channels = 0;
  unsigned char* pixels = stbi_load_from_memory(reinterpret_cast<const unsigned char*>(png->data()),
                                                static_cast<int>(png->size()), &w, &h, &channels, 4);
  ASSERT_NE(pixels, nullptr);
  EXPECT_EQ(w, 64);
  EXPECT_EQ(h, 64);
  EXPECT_TRUE(std::equal(image->rgba.begin(), image->rgba.end(), pixels));
  stbi_image_free(pixels);
}

}  // namespace
}  // namespace lsqsurf::render

namespace lsqsurf::render {
namespace {

// The GL's volume ray casting draws what the CPU reference draws (same rays, samples and
// compositing; the GL samples a 256-texel colour table and computes in single precision).
TEST_F(RenderTest, VolumeShaderMatchesTheCpuReference) {
  VolumeGrid grid;
  const int n = 40;
  grid.dims = {n, n, n};
  grid.origin = core::Vec3d::Constant(-1);
  grid.spacing = core::Vec3d::Constant(2.0 / (n - 1));
  for (int k = 0; k < n; ++k) {
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        const core::Vec3d x = grid.origin + grid.spacing.cwiseProduct(core::Vec3d(i, j, k));
        const bool inside = x.z() > -0.6;  // The bottom is outside the data.
        grid.values.push_back(inside ? static_cast<float>(std::sin(3 * x.x()) * std::cos(2 * x.y()) + x.z())
                                     : std::numeric_limits<float>::quiet_NaN());
        grid.gradients.push_back(core::Vec3f(static_cast<float>(3 * std::cos(3 * x.x()) * std::cos(2 * x.y())),
                                             static_cast<float>(-2 * std::sin(3 * x.x()) * std::sin(2 * x.y())), 1.0f));
      }
    }
  }
  for (const VolumeMode mode : {VolumeMode::kDirect, VolumeMode::kIsosurface}) {
    RenderParams p;
    p.width = p.height = 128;
    p.volume_mode = mode;
    p.iso_value = 0.3;
    auto gpu = renderer_->RenderVolume(grid, p);
    auto cpu = RaycastVolume(grid, p);
    ASSERT_TRUE(gpu.ok()) << gpu.status();
    ASSERT_TRUE(cpu.ok()) << cpu.status();
    int drawn = 0;  // Pixels that are not the white background.
    for (size_t i = 0; i < cpu->rgba.size(); i += 4) drawn += cpu->rgba[i] < 250 || cpu->rgba[i + 2] < 250;
    int gpu_drawn = 0;
    for (size_t i = 0; i < gpu->rgba.size(); i += 4) gpu_drawn += gpu->rgba[i] < 250 || gpu->rgba[i + 2] < 250;
    EXPECT_GT(drawn, 128 * 128 / 10);
    EXPECT_NEAR(gpu_drawn, drawn, drawn / 100);
    std::vector<int> differences;
    double sum = 0;
    for (size_t i = 0; i < cpu->rgba.size(); ++i) {
      const int d = std::abs(static_cast<int>(cpu->rgba[i]) - static_cast<int>(gpu->rgba[i]));
      differences.push_back(d);
      sum += d;
    }
    std::sort(differences.begin(), differences.end());
    const double mean = sum / static_cast<double>(differences.size());
    std::printf("mode %d: mean difference %.3f, 99th percentile %d\n", static_cast<int>(mode), mean,
                differences[differences.size() * 99 / 100]);
    EXPECT_LT(mean, 1.5);
    EXPECT_LE(differences[differences.size() * 99 / 100], 16);
  }
}

}  // namespace
}  // namespace lsqsurf::render
