#include "worker/volume/synthetic.h"

#include <cmath>
#include <numbers>
#include <random>

namespace lsqsurf::volume {
namespace {

// Central differences in double: the error (~1e-10 relative) is far below anything measured.
std::function<Vec3d(const Vec3d&)> NumericGradient(std::function<double(const Vec3d&)> f) {
  return [f = std::move(f)](const Vec3d& x) {
    constexpr double kStep = 1e-6;
    Vec3d g;
    for (int a = 0; a < 3; ++a) {
      Vec3d lo = x, hi = x;
      lo[a] -= kStep;
      hi[a] += kStep;
      g[a] = (f(hi) - f(lo)) / (2 * kStep);
    }
    return g;
  };
}

}  // namespace

AnalyticField Franke3d() {
  auto f = [](const Vec3d& p) {
    const double x = 9 * p.x(), y = 9 * p.y(), z = 9 * p.z();
    auto sq = [](double v) { return v * v; };
    return 0.75 * std::exp(-(sq(x - 2) + sq(y - 2) + sq(z - 2)) / 4) +
           0.75 * std::exp(-sq(x + 1) / 49 - (y + 1) / 10 - (z + 1) / 10) +
           0.5 * std::exp(-(sq(x - 7) + sq(y - 3) + sq(z - 5)) / 4) -
           0.2 * std::exp(-sq(x - 4) - sq(y - 7) - sq(z - 5));
  };
  return {"franke", f, NumericGradient(f), core::Box3(Vec3d(0, 0, 0), Vec3d(1, 1, 1))};
}

AnalyticField MarschnerLobb() {
  auto f = [](const Vec3d& p) {
    constexpr double kAlpha = 0.25, kFrequency = 6;
    const double r = std::hypot(p.x(), p.y());
    const double pi = std::numbers::pi;
    return (1 - std::sin(pi * p.z() / 2) + kAlpha * (1 + std::cos(2 * pi * kFrequency * std::cos(pi * r / 2)))) /
           (2 * (1 + kAlpha));
  };
  return {"marschner_lobb", f, NumericGradient(f), core::Box3(Vec3d(-1, -1, -1), Vec3d(1, 1, 1))};
}

VolumeMesh JitteredTetMesh(const core::Box3& domain, int n, double jitter, uint64_t seed) {
  VolumeMesh hex;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(-1, 1);
  const Vec3d step = domain.sizes() / (n - 1);
  for (int k = 0; k < n; ++k) {
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        Vec3d p = domain.min() + Vec3d(i, j, k).cwiseProduct(step);
        const bool interior = i > 0 && j > 0 && k > 0 && i < n - 1 && j < n - 1 && k < n - 1;
        if (interior && jitter > 0) {
          Vec3d d;
          do {
            d = Vec3d(unit(rng), unit(rng), unit(rng));
          } while (d.squaredNorm() > 1);
          p += jitter * step.minCoeff() * d;
        }
        hex.positions.push_back(p.cast<float>());
      }
    }
  }
  AddStructuredHexahedra(hex, n, n, n);
  VolumeMesh out;
  out.positions = std::move(hex.positions);
  for (const auto& t : Tetrahedralize(hex)) out.AddCell(CellType::kTetrahedron, t);
  return out;
}

VolumeMesh StretchedCurvilinearGrid(const core::Box3& domain, int nx, int ny, int nz, double ratio) {
  VolumeMesh out;
  const Vec3d lo = domain.min(), size = domain.sizes();
  const double pi = std::numbers::pi;
  for (int k = 0; k < nz; ++k) {
    // Geometric grading: the first cell is the thinnest, each next one `ratio` times taller.
    const double t =
        ratio == 1 ? static_cast<double>(k) / (nz - 1) : (std::pow(ratio, k) - 1) / (std::pow(ratio, nz - 1) - 1);
    for (int j = 0; j < ny; ++j) {
      for (int i = 0; i < nx; ++i) {
        const double u = static_cast<double>(i) / (nx - 1), v = static_cast<double>(j) / (ny - 1);
        // The x lines bow by up to 6 % of the width, less towards the top.
        const double x = lo.x() + size.x() * (u + 0.06 * std::sin(pi * v) * (1 - t) * u * (1 - u) * 4);
        out.positions.push_back(Vec3d(x, lo.y() + size.y() * v, lo.z() + size.z() * t).cast<float>());
      }
    }
  }
  AddStructuredHexahedra(out, nx, ny, nz);
  return out;
}

VolumeMesh ScatteredPoints(const core::Box3& domain, int64_t count, uint64_t seed) {
  VolumeMesh out;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0, 1);
  out.positions.reserve(static_cast<size_t>(count));
  for (int64_t i = 0; i < count; ++i) {
    const Vec3d t(unit(rng), unit(rng), unit(rng));
    out.positions.push_back((domain.min() + t.cwiseProduct(domain.sizes())).cast<float>());
  }
  return out;
}

void SampleField(VolumeMesh& mesh, const AnalyticField& field) {
  VertexField f{field.name, 1, {}};
  f.values.reserve(mesh.vertex_count());
  for (const Vec3f& p : mesh.positions) f.values.push_back(static_cast<float>(field.value(p.cast<double>())));
  for (VertexField& existing : mesh.fields) {
    if (existing.name == field.name) {
      existing = std::move(f);
      return;
    }
  }
  mesh.fields.push_back(std::move(f));
}

}  // namespace lsqsurf::volume
