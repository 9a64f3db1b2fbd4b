#include "worker/render/face_culling.h"

#include <cstdint>

#include "worker/core/mesh_metrics.h"

namespace lsqsurf::render {
OutsideWinding ClosedMeshOutsideWinding(std::span<const core::Vec3f> vertices, std::span<const core::Vec3f> normals,
                                        std::span<const core::Triangle> faces) {
  if (faces.empty()) return OutsideWinding::kUnknown;
  // Sum of hash(a→b) − hash(b→a) over all directed edges: zero when each edge is matched by its
  // reverse, so the surface has no boundary and neighbouring faces agree on orientation.
  uint64_t unmatched = 0;
  const bool use_normals = normals.size() == vertices.size();
  int64_t agree = 0, disagree = 0;
  double six_volume = 0;
  for (const core::Triangle& f : faces) {
    unmatched += core::UnmatchedEdgeSum(f);
    const core::Vec3f &p = vertices[f[0]], &q = vertices[f[1]], &r = vertices[f[2]];
    if (use_normals) {
      const float s = (q - p).cross(r - p).dot(normals[f[0]] + normals[f[1]] + normals[f[2]]);
      agree += s > 0;
      disagree += s < 0;
    }
    six_volume += p.cast<double>().dot(q.cast<double>().cross(r.cast<double>()));
  }
  if (unmatched != 0 || six_volume == 0) return OutsideWinding::kUnknown;
  const OutsideWinding by_volume = six_volume > 0 ? OutsideWinding::kCounterClockwise : OutsideWinding::kClockwise;
  if (!use_normals) return by_volume;
  // The normals must agree face by face (a component wound the other way breaks the 99 %) and
  // with the volume (normals that point inwards are not trusted).
  const int64_t total = agree + disagree;
  if (total == 0) return OutsideWinding::kUnknown;
  const OutsideWinding by_normals = agree >= total - total / 100      ? OutsideWinding::kCounterClockwise
                                    : disagree >= total - total / 100 ? OutsideWinding::kClockwise
                                                                      : OutsideWinding::kUnknown;
  return by_normals == by_volume ? by_volume : OutsideWinding::kUnknown;
}

}  // namespace lsqsurf::render
