// lsqsurf-volume-bench — the volume engine on analytic fields with known truth, beside the
// piecewise-linear answer on the same mesh (BENCHMARKS.md "Volume data").
//
// Per case: the upload's size against the binary legacy VTK file, the precomputation's time and
// the process's peak memory, the field's RMS and largest error at random interior points for
// iaMLS and for linear interpolation, the gradient's relative RMS error, 1M probes timed for both,
// and the isosurface's mean and largest first-order distance to the true level, against the
// linear contour's (its crossings on the tetrahedra's edges). Run one case per process for a
// peak memory that belongs to that case alone.
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>

#include "worker/io/files.h"
#include "worker/io/volume_codec.h"
#include "worker/io/volume_formats.h"
#include "worker/volume/cell_locator.h"
#include "worker/volume/synthetic.h"
#include "worker/volume/volume_field.h"
#include "worker/volume/volume_isosurface.h"

namespace {

using lsqsurf::core::Box3;
using lsqsurf::core::Vec3d;
using lsqsurf::core::Vec3f;
namespace volume = lsqsurf::volume;
using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) { return std::chrono::duration<double>(Clock::now() - since).count(); }

double PeakMib() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;
}

struct Case {
  std::string name;
  volume::AnalyticField field;
  volume::VolumeMesh mesh;
  double iso = 0;
};

Case MakeCase(const std::string& name, int n) {
  const bool ml = name.starts_with("ml");
  Case c{name, ml ? volume::MarschnerLobb() : volume::Franke3d(), {}, ml ? 0.5 : 0.35};
  if (name.ends_with("-tets")) {
    c.mesh = volume::JitteredTetMesh(c.field.domain, n, 0.3, 1);
  } else if (name.ends_with("-curvilinear")) {
    c.mesh = volume::StretchedCurvilinearGrid(c.field.domain, n, n, n, 1.05);
  } else {
    c.mesh = volume::ScatteredPoints(c.field.domain, static_cast<int64_t>(n) * n * n, 1);
  }
  volume::SampleField(c.mesh, c.field);
  return c;
}

double LevelDistance(const volume::AnalyticField& f, const Vec3d& x, double iso) {
  return std::abs(f.value(x) - iso) / f.gradient(x).norm();
}

void ReportUpload(const Case& c) {
  const std::vector<std::string> names = {c.field.name};
  auto vertices = lsqsurf::io::EncodeVolumeVertices(c.mesh, names, {});
  const std::string cells = c.mesh.has_cells() ? lsqsurf::io::EncodeCellStream(c.mesh) : std::string();
  const size_t vtk = lsqsurf::io::EncodeLegacyVtk(c.mesh, true).size();
  if (!vertices.ok()) return;
  std::printf("  upload: %zu B vertices + %zu B cells = %.3g MB vs binary .vtk %.3g MB (%.1fx smaller)\n",
              vertices->size(), cells.size(), static_cast<double>(vertices->size() + cells.size()) / 1e6,
              static_cast<double>(vtk) / 1e6,
              static_cast<double>(vtk) / static_cast<double>(vertices->size() + cells.size()));
}

// Field and gradient errors at `count` random points inside the middle 80 % of the domain, and
// 1M probes timed for both methods.
void ReportField(const Case& c, const volume::VolumeField& field, const volume::CellLocator* locator, int count,
                 int probes) {
  const Box3 d = c.field.domain;
  const Box3 inner(d.min() + 0.1 * d.sizes(), d.max() - 0.1 * d.sizes());
  std::mt19937_64 rng(17);
  std::uniform_real_distribution<double> unit(0, 1);
  std::vector<Vec3d> xs(static_cast<size_t>(std::max(count, probes)));
  for (Vec3d& x : xs) x = inner.min() + Vec3d(unit(rng), unit(rng), unit(rng)).cwiseProduct(inner.sizes());
  std::vector<volume::VolumeField::Sample> samples(xs.size());
  const auto start = Clock::now();
  (void)field.EvaluateBatch({xs.data(), static_cast<size_t>(probes)}, 0, samples);
  const double probe_seconds = Seconds(start);
  if (count > probes) {  // The error points beyond the timed probes, untimed.
    const auto rest = static_cast<size_t>(probes);
    (void)field.EvaluateBatch({xs.data() + rest, xs.size() - rest}, 0, std::span(samples).subspan(rest));
  }
  double sum = 0, worst = 0, lsum = 0, lworst = 0, gerr = 0, gnorm = 0;
  const auto& values = c.mesh.fields[0].values;
  double linear_seconds = 0;
  if (locator != nullptr) {
    const auto lstart = Clock::now();
    double checksum = 0;
    for (int i = 0; i < probes; ++i) {
      const auto at = locator->Locate(xs[static_cast<size_t>(i)]);
      if (at.tet >= 0) checksum += locator->Interpolate(values, 1, 0, at);
    }
    linear_seconds = Seconds(lstart);
    if (checksum == 1e300) std::printf("?");  // Keeps the loop from being optimised away.
  }
  for (int i = 0; i < count; ++i) {
    const Vec3d& x = xs[static_cast<size_t>(i)];
    const double exact = c.field.value(x);
    const double e = samples[static_cast<size_t>(i)].value - exact;
    sum += e * e;
    worst = std::max(worst, std::abs(e));
    gerr += (samples[static_cast<size_t>(i)].gradient - c.field.gradient(x)).squaredNorm();
    gnorm += c.field.gradient(x).squaredNorm();
    if (locator != nullptr) {
      const auto at = locator->Locate(x);
      const double l = locator->Interpolate(values, 1, 0, at) - exact;
      lsum += l * l;
      lworst = std::max(lworst, std::abs(l));
    }
  }
  std::printf("  field: iaMLS RMS %.3g max %.3g | gradient rel RMS %.3g", std::sqrt(sum / count), worst,
              std::sqrt(gerr / gnorm));
  if (locator != nullptr) {
    std::printf(" | linear RMS %.3g max %.3g | ratio %.2f", std::sqrt(lsum / count), lworst,
                std::sqrt(sum / count) / std::sqrt(lsum / count));
  }
  std::printf("\n  probes: %d iaMLS %.3f s", probes, probe_seconds);
  if (locator != nullptr) std::printf(", linear (locator + interpolation, 1 thread) %.3f s", linear_seconds);
  std::printf("\n");
}

void ReportIsosurface(const Case& c, const volume::VolumeField& field, const volume::CellLocator* locator) {
  lsqsurf::core::LocalJobContext ctx;
  volume::VolumeIsosurfaceParams params;
  params.iso_values = {c.iso};
  const auto start = Clock::now();
  auto mesh = volume::ExtractVolumeIsosurface(field, params, ctx);
  const double seconds = Seconds(start);
  if (!mesh.ok()) {
    std::printf("  isosurface: %s\n", std::string(mesh.status().message()).c_str());
    return;
  }
  double sum = 0, worst = 0;
  for (const Vec3f& v : mesh->vertices) {
    const double d = LevelDistance(c.field, v.cast<double>(), c.iso);
    sum += d;
    worst = std::max(worst, d);
  }
  std::printf("  isosurface %g: %zu triangles in %.2f s, mean distance %.3g max %.3g", c.iso, mesh->faces.size(),
              seconds, sum / static_cast<double>(mesh->vertices.size()), worst);
  if (locator != nullptr) {
    double lsum = 0, lworst = 0;
    int64_t count = 0;
    const auto& values = c.mesh.fields[0].values;
    for (const auto& t : locator->tets()) {
      for (int a = 0; a < 4; ++a) {
        for (int b = a + 1; b < 4; ++b) {
          const double fa = values[t[a]] - c.iso, fb = values[t[b]] - c.iso;
          if ((fa < 0) == (fb < 0)) continue;
          const double s = fa / (fa - fb);
          const Vec3d x = (1 - s) * c.mesh.positions[t[a]].cast<double>() + s * c.mesh.positions[t[b]].cast<double>();
          const double d = LevelDistance(c.field, x, c.iso);
          lsum += d;
          lworst = std::max(lworst, d);
          ++count;
        }
      }
    }
    std::printf(" | linear contour mean %.3g max %.3g | ratio %.2f", lsum / static_cast<double>(count), lworst,
                (sum / static_cast<double>(mesh->vertices.size())) / (lsum / static_cast<double>(count)));
  }
  std::printf("\n");
}

// The case's mesh from a file, made fit for the engine as a server would, its field sampled.
bool ReadCaseMesh(const std::string& path, Case& c) {
  auto mesh = lsqsurf::io::ReadVolumeFile(path);
  if (!mesh.ok()) {
    std::printf("%s\n", std::string(mesh.status().message()).c_str());
    return false;
  }
  mesh->fields.clear();
  const auto start = Clock::now();
  auto repairs = volume::RepairVolumeMesh(*mesh);
  if (!repairs.ok()) {
    std::printf("%s: %s\n", path.c_str(), std::string(repairs.status().message()).c_str());
    return false;
  }
  std::printf(
      "%s: repaired in %.2f s: %lld linearised, %lld reoriented, %lld degenerate cells; %lld merged, %lld unused "
      "vertices\n",
      path.c_str(), Seconds(start), static_cast<long long>(repairs->linearised_cells),
      static_cast<long long>(repairs->reoriented_cells), static_cast<long long>(repairs->degenerate_cells),
      static_cast<long long>(repairs->merged_vertices), static_cast<long long>(repairs->unused_vertices));
  c.mesh = *std::move(mesh);
  volume::SampleField(c.mesh, c.field);
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lsqsurf-volume-bench: the volume engine against analytic truth and linear interpolation"};
  std::vector<std::string> cases = {"franke-tets"};
  int n = 41, samples = 100'000, probes = 1'000'000;
  app.add_option("--cases", cases,
                 "franke-tets | ml-tets | franke-curvilinear | ml-curvilinear | franke-points | ml-points")
      ->capture_default_str();
  app.add_option("--n", n, "vertices per axis (points: n^3 of them)")->capture_default_str();
  app.add_option("--samples", samples, "error sample points")->capture_default_str();
  app.add_option("--probes", probes, "timed probe points")->capture_default_str();
  std::string write, mesh_file;
  app.add_option("--write", write, "also write each case's mesh as binary legacy VTK: PREFIX-CASE.vtk");
  app.add_option("--mesh", mesh_file,
                 "the cases' mesh from this .vtk/.vtu file instead (as other tools write it: repaired first, the "
                 "case's field sampled at its vertices)");
  volume::VolumeFieldParams params;
  app.add_option("--epsilon", params.epsilon, "kernel shape; 0 = cross-validation")->capture_default_str();
  app.add_option("--iterations", params.iterations, "-1 = cross-validation")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  for (const std::string& name : cases) {
    Case c = MakeCase(name, n);
    if (!mesh_file.empty() && !ReadCaseMesh(mesh_file, c)) return 1;
    std::printf("%s: %zu vertices, %zu cells\n", name.c_str(), c.mesh.vertex_count(), c.mesh.cell_count());
    ReportUpload(c);
    if (!write.empty()) {
      const std::string path = write + "-" + name + ".vtk";
      if (absl::Status s = lsqsurf::io::WriteFileAtomically(path, lsqsurf::io::EncodeLegacyVtk(c.mesh, true));
          !s.ok()) {
        std::printf("  cannot write %s: %s\n", path.c_str(), std::string(s.message()).c_str());
      }
    }
    lsqsurf::core::LocalJobContext ctx;
    const std::vector<std::string> names = {c.field.name};
    const auto start = Clock::now();
    auto field = volume::BuildVolumeField(c.mesh, names, params, ctx);
    if (!field.ok()) {
      std::printf("  failed: %s\n", std::string(field.status().message()).c_str());
      continue;
    }
    const auto& st = (*field)->stats();
    std::printf(
        "  precomputation: %.2f s, peak RSS %.0f MiB; epsilon %.3g, %d iterations (cross-validation RMS %.3g "
        "on %d held-out vertices), spectral radius %.4f, %.0f kernels per vertex\n",
        Seconds(start), PeakMib(), st.epsilon, st.iterations, st.cross_validation_rms, st.cross_validation_points,
        st.spectral_radius, st.kernels_per_vertex);
    ReportField(c, **field, (*field)->locator(), samples, probes);
    ReportIsosurface(c, **field, (*field)->locator());
  }
  return 0;
}
