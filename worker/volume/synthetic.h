// worker/volume/synthetic.h — analytic fields and generated meshes with known truth, for the
// tests, the benchmark and the bundled samples (BENCHMARKS.md "Volume data").
#pragma once

#include <cstdint>
#include <functional>
#include <string>

#include "worker/volume/volume_mesh.h"

namespace lsqsurf::volume {

struct AnalyticField {
  std::string name;
  std::function<double(const Vec3d&)> value;
  std::function<Vec3d(const Vec3d&)> gradient;
  core::Box3 domain;  // Where it is defined for the benchmark's meshes.
};

// Franke's function in 3-D on [0, 1]³.
AnalyticField Franke3d();
// Marschner–Lobb on [−1, 1]³ (f_M = 6, α = 0.25); its classic isosurface is 0.5.
AnalyticField MarschnerLobb();

// An n³ vertex lattice of `domain`, interior vertices jittered uniformly within a ball of
// `jitter` × spacing (deterministic for a seed), each cube cut into the 6 Kuhn tetrahedra.
VolumeMesh JitteredTetMesh(const core::Box3& domain, int n, double jitter, uint64_t seed);
// An nx × ny × nz structured grid of hexahedra over `domain`, its vertices graded towards the
// low-z face (cell heights growing geometrically by `ratio`) and bent (the x lines curve), like
// the boundary-layer grids of CFD: thin, stretched and curved cells.
VolumeMesh StretchedCurvilinearGrid(const core::Box3& domain, int nx, int ny, int nz, double ratio);
// `count` points uniformly at random in `domain`, no cells.
VolumeMesh ScatteredPoints(const core::Box3& domain, int64_t count, uint64_t seed);

// Adds (or replaces) a scalar field sampled from `field` at every vertex, named field.name.
void SampleField(VolumeMesh& mesh, const AnalyticField& field);

}  // namespace lsqsurf::volume
