// worker/core/local_spacing.h — a cloud's sampling spacing where it is, not on average.
//
// A lidar's or a depth camera's spacing grows with range, so one global spacing calls the far
// side of a scan unmeasured and the near side measured however far a surface strays. The local
// spacing at a query is the median, over its `kAround` nearest points, of each one's distance to
// its nearest other point: the median ignores a duplicate or an outlier among them, and 24 of
// them keep the chance gaps of an even sampling from reading as unmeasured (with 8, the median
// varies so much that 1.5 % of a clean sample's surface lay beyond 3 spacings; with 24, 0.6 %;
// by the cloud's one median spacing, 0.2 %).
#pragma once

#include <span>
#include <vector>

#include "worker/core/geometry.h"
#include "worker/core/job_context.h"
#include "worker/core/kd_tree.h"

namespace lsqsurf::core {

// How many local spacings from every point a query must lie to count as unmeasured: the job's
// `filled` marking and the sensor report share it.
inline constexpr double kUnmeasuredSpacings = 3.0;

// A face of a mesh whose vertices carry unmeasured marks (0 or 1) counts as unmeasured where
// most of its corners are: the job's shell removal and the sensor report's precision share it.
inline bool FaceUnmeasured(std::span<const float> marks, const Triangle& face) {
  return marks[face[0]] + marks[face[1]] + marks[face[2]] >= 1.5f;
}

class LocalSpacing {
 public:
  static constexpr size_t kAround = 24;

  // Measures every point's nearest distance in parallel (cancellation leaves the rest 0, which
  // the caller sees in ctx). `tree` must outlive this object.
  explicit LocalSpacing(const KdTree& tree, const JobContext* ctx = nullptr);

  struct Reading {
    double nearest = 0;  // Distance from the query to its nearest point.
    double spacing = 0;  // The local spacing there.
    // The query lies farther than `spacings` local spacings from every point.
    bool Beyond(double spacings) const { return nearest > spacings * spacing; }
    bool Unmeasured() const { return Beyond(kUnmeasuredSpacings); }
  };
  // Thread-safe with one `scratch` per thread.
  Reading At(const Vec3f& query, std::vector<Neighbor>& scratch) const;

  // The cloud's one spacing: the median over all points of the distance to the nearest other
  // point (0 for fewer than two points).
  double MedianNearest() const;

 private:
  const KdTree& tree_;
  std::vector<float> nearest_;  // Per point: the distance to its nearest other point.
};

}  // namespace lsqsurf::core
