#include "worker/pu/tile_files.h"

#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <memory>

#include "worker/core/strings.h"

namespace lsqsurf::pu {
namespace {

constexpr char kScratchPrefix[] = "lsqsurf-tiles-";

}  // namespace

TileGrid TileGrid::AtLevel(const core::Vec3d& origin, double root_edge, int level) {
  return TileGrid{origin, std::ldexp(root_edge, -level), level, int64_t{1} << level};
}

std::array<int64_t, 3> TileGrid::CellOf(const core::Vec3d& p) const {
  std::array<int64_t, 3> c{};
  for (int k = 0; k < 3; ++k) {
    const double g = std::floor((p[k] - origin[k]) / edge);
    c[static_cast<size_t>(k)] = g < 0 ? 0 : std::min<int64_t>(static_cast<int64_t>(std::min(g, 4e18)), cells - 1);
  }
  return c;
}

std::array<int64_t, 3> TileGrid::FromKey(uint64_t key) {
  constexpr uint64_t kMask = (uint64_t{1} << 21) - 1;
  return {static_cast<int64_t>(key & kMask), static_cast<int64_t>(key >> 21 & kMask), static_cast<int64_t>(key >> 42)};
}

core::Box3 TileGrid::Cube(const std::array<int64_t, 3>& c) const {
  core::Vec3d lo, hi;
  for (int k = 0; k < 3; ++k) {
    const auto i = static_cast<double>(c[static_cast<size_t>(k)]);
    lo[k] = origin[k] + edge * i;
    hi[k] = origin[k] + edge * (i + 1);
  }
  return core::Box3(lo, hi);
}

absl::StatusOr<ScratchDir> ScratchDir::Create(const std::string& parent) {
  std::error_code error;
  const std::filesystem::path base =
      parent.empty() ? std::filesystem::temp_directory_path(error) : std::filesystem::path(parent);
  if (error) return absl::InternalError(core::StrCat("no temporary directory: ", error.message()));
  // The process's id in the name: a later process can tell the directories of dead ones.
  std::string pattern = (base / core::StrCat(kScratchPrefix, getpid(), "-XXXXXX")).string();
  if (mkdtemp(pattern.data()) == nullptr) {
    return absl::InternalError(
        core::StrCat("cannot make a scratch directory in ", base.string(), ": ", std::strerror(errno)));
  }
  return ScratchDir(pattern);
}

absl::StatusOr<int> SweepAbandonedScratch(const std::string& parent) {
  std::error_code error;
  int removed = 0;
  for (const auto& entry : std::filesystem::directory_iterator(parent, error)) {
    const std::string name = entry.path().filename().string();
    if (!name.starts_with(kScratchPrefix)) continue;
    const long pid = std::strtol(name.c_str() + std::strlen(kScratchPrefix), nullptr, 10);
    // Alive (or not ours to signal): left alone.
    if (pid <= 0 || kill(static_cast<pid_t>(pid), 0) == 0 || errno != ESRCH) continue;
    std::error_code ignored;
    if (std::filesystem::remove_all(entry.path(), ignored) > 0) ++removed;
  }
  if (error) return absl::UnavailableError(core::StrCat("cannot read ", parent, ": ", error.message()));
  return removed;
}

ScratchDir::~ScratchDir() {
  if (path_.empty()) return;
  std::error_code ignored;
  std::filesystem::remove_all(path_, ignored);
}

TileBuckets::TileBuckets(std::string directory, const std::vector<uint64_t>& keys) : directory_(std::move(directory)) {
  for (uint64_t key : keys) buckets_[key];
}

std::string TileBuckets::PathOf(uint64_t key) const { return core::StrCat(directory_, "/tile-", key, ".pts"); }

absl::Status TileBuckets::Add(uint64_t key, const core::Vec3f& position, const core::Vec3f& normal) {
  const auto it = buckets_.find(key);
  if (it == buckets_.end()) return absl::OkStatus();
  Bucket& bucket = it->second;
  bucket.buffer.insert(bucket.buffer.end(),
                       {position.x(), position.y(), position.z(), normal.x(), normal.y(), normal.z()});
  ++bucket.points;
  ++total_points_;
  if (bucket.buffer.size() >= 6 * kBufferRecords) return FlushBucket(key, bucket);
  return absl::OkStatus();
}

// Opened for each flush: a pass may feed thousands of tiles, more than a process may keep open.
absl::Status TileBuckets::FlushBucket(uint64_t key, Bucket& bucket) {
  if (bucket.buffer.empty()) return absl::OkStatus();
  const std::string path = PathOf(key);
  std::unique_ptr<FILE, int (*)(FILE*)> file(std::fopen(path.c_str(), "ab"), &std::fclose);
  if (!file) return absl::InternalError(core::StrCat("cannot write ", path, ": ", std::strerror(errno)));
  if (std::fwrite(bucket.buffer.data(), sizeof(float), bucket.buffer.size(), file.get()) != bucket.buffer.size()) {
    return absl::ResourceExhaustedError(core::StrCat("cannot write ", path, " (disk full?)"));
  }
  bucket.buffer.clear();
  return absl::OkStatus();
}

absl::Status TileBuckets::Flush() {
  for (auto& [key, bucket] : buckets_) {
    if (absl::Status s = FlushBucket(key, bucket); !s.ok()) return s;
    bucket.buffer.shrink_to_fit();
  }
  return absl::OkStatus();
}

int64_t TileBuckets::Points(uint64_t key) const {
  const auto it = buckets_.find(key);
  return it == buckets_.end() ? 0 : it->second.points;
}

absl::StatusOr<core::PointCloud> TileBuckets::Read(uint64_t key, const core::Box3* keep) const {
  core::PointCloud cloud;
  const int64_t points = Points(key);
  if (points == 0) return cloud;
  const std::string path = PathOf(key);
  std::unique_ptr<FILE, int (*)(FILE*)> file(std::fopen(path.c_str(), "rb"), &std::fclose);
  if (!file) return absl::InternalError(core::StrCat("cannot read ", path, ": ", std::strerror(errno)));
  cloud.positions.reserve(static_cast<size_t>(points));
  cloud.normals.reserve(static_cast<size_t>(points));
  std::vector<float> records(6 * kBufferRecords);
  for (size_t done = 0; done < static_cast<size_t>(points);) {
    const size_t n = std::min(kBufferRecords, static_cast<size_t>(points) - done);
    if (std::fread(records.data(), kRecordBytes, n, file.get()) != n) {
      return absl::InternalError(core::StrCat(path, " is shorter than the points written to it"));
    }
    for (size_t i = 0; i < n; ++i) {
      const float* r = &records[6 * i];
      const core::Vec3f p(r[0], r[1], r[2]);
      if (keep != nullptr && !keep->contains(p.cast<double>())) continue;
      cloud.positions.push_back(p);
      cloud.normals.emplace_back(r[3], r[4], r[5]);
    }
    done += n;
  }
  return cloud;
}

absl::Status TileBuckets::Clear() {
  for (auto& [key, bucket] : buckets_) {
    std::error_code ignored;
    std::filesystem::remove(PathOf(key), ignored);
    bucket = {};
  }
  total_points_ = 0;
  return absl::OkStatus();
}

}  // namespace lsqsurf::pu
