// worker/volume/cell_locator.h — which cell of a volume mesh holds a point.
//
// The cells are cut into tetrahedra (see Tetrahedralize) and binned in a BoxGrid by their
// bounding boxes; a query tests the tetrahedra of one bin by barycentric coordinates. This
// decides the data's domain (no isosurface and no probe value outside the cells) and gives the
// piecewise-linear interpolant that the volume engine is measured against.
//
// Thread safety: after construction every query is const and may run concurrently.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "worker/volume/box_grid.h"
#include "worker/volume/volume_mesh.h"

namespace lsqsurf::volume {

class CellLocator {
 public:
  // The mesh must have cells and be valid (ValidateVolumeMesh); its positions are copied.
  explicit CellLocator(const VolumeMesh& mesh);
  // From tetrahedra already cut (Tetrahedralize), e.g. read back from a stored field.
  CellLocator(std::vector<Vec3f> positions, std::vector<std::array<uint32_t, 4>> tets);

  struct Location {
    int64_t tet = -1;                    // Index into tets(); -1 outside every cell.
    std::array<double, 4> weights = {};  // Barycentric coordinates within that tetrahedron.
  };

  // Faces shared by two cells belong to both; points within 1e-6 of a cell's size of the domain's
  // boundary count as inside.
  Location Locate(const Vec3d& x) const;
  bool Contains(const Vec3d& x) const { return Locate(x).tet >= 0; }

  // The linear interpolant of one component of a vertex-major array at a location inside.
  double Interpolate(std::span<const float> values, int components, int component, const Location& at) const;

  std::span<const std::array<uint32_t, 4>> tets() const { return tets_; }
  std::span<const Vec3f> positions() const { return positions_; }

 private:
  std::vector<Vec3f> positions_;
  std::vector<std::array<uint32_t, 4>> tets_;
  BoxGrid grid_;  // The tetrahedra by bounding box.
};

}  // namespace lsqsurf::volume
