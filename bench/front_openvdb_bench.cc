// lsqsurf-front-openvdb-bench — the reference for the front-tracking benchmarks: OpenVDB's
// narrow-band level set (WENO5 in space, TVD-RK3 in time, `LevelSetAdvection`) moved through the
// same velocity fields as `lsqsurf-front-bench` (lsqsurf's own field objects), on a grid of the
// same spacing h, and measured the same way: volume change and E1 = ∫ |χ − χ_exact| dV against
// the exact initial shape (z lines of spacing h/2 across, sampled every h/8 along).
// Built only with the `bench-openvdb` preset (Debian libopenvdb-dev); OpenVDB stays in this file.
#include <openvdb/openvdb.h>
#include <openvdb/tools/Composite.h>
#include <openvdb/tools/Interpolation.h>
#include <openvdb/tools/LevelSetAdvect.h>
#include <openvdb/tools/LevelSetMeasure.h>
#include <openvdb/tools/LevelSetSphere.h>
#include <openvdb/tools/MeshToVolume.h>
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>

#include "worker/front/front_tracking.h"

namespace {

using lsqsurf::core::Vec3d;

// An lsqsurf velocity field in the shape LevelSetAdvection samples: world positions, world units.
class Field {
 public:
  using ValueType = float;
  using VectorType = openvdb::Vec3f;
  explicit Field(const lsqsurf::front::VelocityField* v) : v_(v) {}
  openvdb::math::Transform transform() const { return openvdb::math::Transform(); }
  VectorType operator()(const openvdb::Vec3d& x, ValueType t) const {
    const Vec3d u = v_->At(Vec3d(x[0], x[1], x[2]), t);
    return VectorType(static_cast<float>(u.x()), static_cast<float>(u.y()), static_cast<float>(u.z()));
  }
  VectorType operator()(const openvdb::Coord& ijk, ValueType t) const { return (*this)(ijk.asVec3d(), t); }

 private:
  const lsqsurf::front::VelocityField* v_;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf-front-openvdb-bench: OpenVDB level-set reference for the Zalesak and Enright tests"};
  std::string test = "enright";
  int cells = 128;
  double period = 3.0;
  int frames = 8;
  app.add_option("--test", test, "zalesak | enright")->capture_default_str();
  app.add_option("--cells", cells, "grid cells per unit (voxel size h = 1/cells)")->capture_default_str();
  app.add_option("--period", period, "Enright period T")->capture_default_str();
  app.add_option("--frames", frames, "print this many frames after the start")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  const bool zalesak = test == "zalesak";
  if (!zalesak && test != "enright") return std::fprintf(stderr, "unknown --test %s\n", test.c_str()), 2;
  if (cells < 16 || cells > 512 || frames < 1) return std::fprintf(stderr, "--cells in 16..512, --frames ≥ 1\n"), 2;
  openvdb::initialize();
  const double h = 1.0 / cells;
  const auto shape = zalesak ? lsqsurf::front::InitialShape::kZalesakSphere : lsqsurf::front::InitialShape::kSphere;

  openvdb::FloatGrid::Ptr grid;
  if (zalesak) {
    grid = openvdb::tools::createLevelSetSphere<openvdb::FloatGrid>(0.15f, openvdb::Vec3f(0.5f, 0.75f, 0.5f),
                                                                    static_cast<float>(h));
    // The slot: 0.05 wide, from below the sphere up to y = 0.725, through the whole sphere in z.
    const openvdb::math::BBox<openvdb::Vec3s> slot(openvdb::Vec3s(0.475f, 0.55f, 0.3f),
                                                   openvdb::Vec3s(0.525f, 0.725f, 0.7f));
    auto box = openvdb::tools::createLevelSetBox<openvdb::FloatGrid>(slot, grid->transform());
    openvdb::tools::csgDifference(*grid, *box);
  } else {
    grid = openvdb::tools::createLevelSetSphere<openvdb::FloatGrid>(0.15f, openvdb::Vec3f(0.35f, 0.35f, 0.35f),
                                                                    static_cast<float>(h));
  }
  // E1 over the box holding both the level set's narrow band and the exact shape.
  auto shape_error = [&]() {
    const openvdb::CoordBBox active = grid->evalActiveVoxelBoundingBox();
    const openvdb::Vec3d lo = grid->indexToWorld(active.min()), hi = grid->indexToWorld(active.max());
    const Vec3d centre = zalesak ? Vec3d(0.5, 0.75, 0.5) : Vec3d(0.35, 0.35, 0.35);
    Vec3d box_lo, box_hi;
    for (int a = 0; a < 3; ++a) {
      box_lo[a] = std::min(lo[a], centre[a] - 0.15) - h;
      box_hi[a] = std::max(hi[a], centre[a] + 0.15) + h;
    }
    openvdb::tools::GridSampler<openvdb::FloatGrid, openvdb::tools::BoxSampler> sampler(*grid);
    const double across = 0.5 * h, along = h / 8;
    double e1 = 0;
    for (double x = std::ceil(box_lo.x() / across) * across; x <= box_hi.x(); x += across) {
      for (double y = std::ceil(box_lo.y() / across) * across; y <= box_hi.y(); y += across) {
        for (double z = box_lo.z() + 0.5 * along; z < box_hi.z(); z += along) {
          const bool inside = sampler.wsSample(openvdb::Vec3d(x, y, z)) < 0;
          if (inside != (lsqsurf::front::ShapeValue(shape, Vec3d(x, y, z)) < 0)) e1 += along;
        }
      }
    }
    return e1 * across * across;
  };
  const double e1_initial = shape_error();
  const auto start = std::chrono::steady_clock::now();  // Advection only, like lsqsurf-front-bench's wall.
  const auto velocity = zalesak ? lsqsurf::front::ZalesakRotation() : lsqsurf::front::EnrightDeformation(period);
  const double end_time = zalesak ? 628.0 : period;
  openvdb::tools::LevelSetAdvection<openvdb::FloatGrid, Field> advect(*grid, Field(velocity.get()));
  advect.setSpatialScheme(openvdb::math::HJWENO5_BIAS);
  advect.setTemporalScheme(openvdb::math::TVD_RK3);

  std::printf("openvdb %s h=1/%d%s\n", test.c_str(), cells, zalesak ? "" : (" T=" + std::to_string(period)).c_str());
  std::printf("%9s %12s %12s %9s\n", "time", "volume", "change_%", "wall_s");
  const double volume0 = openvdb::tools::levelSetVolume(*grid);
  double volume = volume0;
  // LevelSetAdvection samples the field once per step, at its start, and sizes the step by the
  // speed there (and stops where that is nearly zero). Near t = T/2, where Enright's field
  // vanishes, an uncapped step would span much of the reversal with the start's velocity, so
  // steps are capped at h/4 time units, below the CFL step at the field's peak speed of 2.
  const double cap = zalesak ? end_time : 0.25 * h;
  for (int f = 0; f <= frames; ++f) {
    const double t = end_time * f / frames;
    if (f > 0) {
      const double from = end_time * (f - 1) / frames;
      const int pieces = static_cast<int>(std::ceil((t - from) / cap - 1e-9));
      for (int k = 0; k < pieces; ++k) {
        advect.advect(static_cast<float>(from + (t - from) * k / pieces),
                      static_cast<float>(from + (t - from) * (k + 1) / pieces));
      }
    }
    volume = openvdb::tools::levelSetVolume(*grid);
    std::printf("%9.3f %12.6e %12.4f %9.2f\n", t, volume, 100 * (volume - volume0) / volume0,
                std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
    std::fflush(stdout);
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  struct rusage usage {};
  ::getrusage(RUSAGE_SELF, &usage);
  const double e1 = shape_error();
  std::printf("summary: volume_change=%.4f%% e1_rel=%.4f%% (initial level set: %.4f%%) wall=%.1fs peak_rss=%.0fMiB\n",
              100 * (volume - volume0) / volume0, 100 * e1 / volume0, 100 * e1_initial / volume0, seconds,
              static_cast<double>(usage.ru_maxrss) / 1024.0);
  return 0;
}
