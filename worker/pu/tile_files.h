// worker/pu/tile_files.h — the tiles of a tiled PU build and the files their points wait in
// (internal to worker/pu).
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::pu {

// The cubes of one level of the fitting octree, named by a key of their integer corner.
struct TileGrid {
  core::Vec3d origin = core::Vec3d::Zero();
  double edge = 0;
  int level = 0;
  int64_t cells = 1;  // Per axis.

  static TileGrid AtLevel(const core::Vec3d& origin, double root_edge, int level);
  std::array<int64_t, 3> CellOf(const core::Vec3d& p) const;
  static uint64_t Key(const std::array<int64_t, 3>& c) {
    return static_cast<uint64_t>(c[0]) | static_cast<uint64_t>(c[1]) << 21 | static_cast<uint64_t>(c[2]) << 42;
  }
  static std::array<int64_t, 3> FromKey(uint64_t key);
  // From the integer corner alone, so that neighbours agree on their common side.
  core::Box3 Cube(const std::array<int64_t, 3>& c) const;
  // Calls visit(key) for every cell whose cube grown by `reach` meets `box`.
  template <typename Visit>
  void ForEachCellMeeting(const core::Box3& box, double reach, Visit&& visit) const {
    const auto lo = CellOf(box.min() - core::Vec3d::Constant(reach));
    const auto hi = CellOf(box.max() + core::Vec3d::Constant(reach));
    for (int64_t z = lo[2]; z <= hi[2]; ++z)
      for (int64_t y = lo[1]; y <= hi[1]; ++y)
        for (int64_t x = lo[0]; x <= hi[0]; ++x) visit(Key({x, y, z}));
  }
  // Calls visit(key) for every cell whose cube grown by `reach` holds p.
  template <typename Visit>
  void ForEachCellNear(const core::Vec3d& p, double reach, Visit&& visit) const {
    ForEachCellMeeting(core::Box3(p, p), reach, std::forward<Visit>(visit));
  }
};

// A directory of its own under `parent` (the system's temporary directory when empty), removed
// with everything in it when this goes.
class ScratchDir {
 public:
  static absl::StatusOr<ScratchDir> Create(const std::string& parent);
  ScratchDir(ScratchDir&& other) noexcept : path_(std::move(other.path_)) { other.path_.clear(); }
  ScratchDir& operator=(ScratchDir&&) = delete;
  ScratchDir(const ScratchDir&) = delete;
  ~ScratchDir();
  const std::string& path() const { return path_; }

 private:
  explicit ScratchDir(std::string path) : path_(std::move(path)) {}
  std::string path_;
};

// Oriented points appended to one file per tile (6 floats each), buffered so that a bucket pass
// over a huge cloud holds a small buffer per tile, not the points.
class TileBuckets {
 public:
  TileBuckets(std::string directory, const std::vector<uint64_t>& keys);
  // Only keys given to the constructor are kept; others are ignored.
  absl::Status Add(uint64_t key, const core::Vec3f& position, const core::Vec3f& normal);
  absl::Status Flush();
  int64_t Points(uint64_t key) const;
  int64_t TotalBytes() const { return total_points_ * kRecordBytes; }
  // The tile's points, with `keep` only those inside it.
  absl::StatusOr<core::PointCloud> Read(uint64_t key, const core::Box3* keep = nullptr) const;
  absl::Status Clear();  // Empties every file.

 private:
  static constexpr int64_t kRecordBytes = 6 * sizeof(float);
  static constexpr size_t kBufferRecords = 2048;
  struct Bucket {
    std::vector<float> buffer;
    int64_t points = 0;
  };
  std::string PathOf(uint64_t key) const;
  absl::Status FlushBucket(uint64_t key, Bucket& bucket);

  std::string directory_;
  absl::flat_hash_map<uint64_t, Bucket> buckets_;
  int64_t total_points_ = 0;
};

}  // namespace lsqsurf::pu
