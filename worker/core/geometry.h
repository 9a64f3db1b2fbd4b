// worker/core/geometry.h — the data types every engine and codec shares.
//
// Positions and normals are stored as single-precision floats (12 bytes each): a 16M-point
// scan stays under 400 MB of positions. Engines compute in double where accuracy needs it.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace lsqsurf::core {

using Vec3f = Eigen::Vector3f;
using Vec3d = Eigen::Vector3d;
using Box3 = Eigen::AlignedBox3d;

// A named per-element scalar (e.g. "intensity", "degree"); `values` has one entry per element.
struct ScalarAttribute {
  std::string name;
  std::vector<float> values;
};

// Colour travels as three scalars of these names, 0..255 (as a PLY's uchar colour reads).
inline constexpr std::array<const char*, 3> kColourChannels = {"red", "green", "blue"};

// The red, green and blue attributes among `attributes` that hold `count` values each, in that
// order; all three null unless every one is there.
std::array<const ScalarAttribute*, 3> ColourChannels(std::span<const ScalarAttribute> attributes, size_t count);
// Element `i`'s colour as 0xRRGGBB (each channel rounded and clamped to 0..255), from
// ColourChannels' non-null three.
uint32_t PackedColour(const std::array<const ScalarAttribute*, 3>& channels, size_t i);

// An unorganized point set with optional unit normals and optional named scalars.
struct PointCloud {
  std::vector<Vec3f> positions;  // Model units.
  std::vector<Vec3f> normals;    // Empty, or one unit vector per point (outward).
  std::vector<ScalarAttribute> attributes;

  size_t size() const { return positions.size(); }
  bool empty() const { return positions.empty(); }
  bool has_normals() const { return !normals.empty() && normals.size() == positions.size(); }
};

using Triangle = std::array<uint32_t, 3>;

// An indexed triangle mesh; faces are counter-clockwise seen from outside.
struct TriangleMesh {
  std::vector<Vec3f> vertices;                     // Model units.
  std::vector<Triangle> faces;                     // Indices into `vertices`.
  std::vector<Vec3f> normals;                      // Empty, or one per vertex.
  std::vector<ScalarAttribute> vertex_attributes;  // Each with one value per vertex.

  bool empty() const { return faces.empty(); }
};

// Smallest axis-aligned box that holds every point; empty box for no points.
Box3 BoundingBox(std::span<const Vec3f> points);

// Length of the box diagonal, 0 for an empty box.
double Diagonal(const Box3& box);

// Indices of `points` sorted along a Morton (Z-order) curve over their bounding box, so that
// points close in space end up close in the order (cache locality for neighbour sums).
std::vector<uint32_t> MortonOrder(std::span<const Vec3f> points);

// Indices of `points` in lexicographic order of their positions (x, then y, then z; ties by index).
std::vector<uint32_t> PositionOrder(std::span<const Vec3f> points);

// Renumbers `mesh`'s vertices in PositionOrder, coincident ones by their normal and their faces'
// other corners (normals and vertex attributes with them), and sorts
// its faces, each rotated to start at its lowest vertex (orientation kept). Why: a parallel
// extraction's vertex order varies from run to run, and whatever walks the mesh by index (hole
// filling's loops, its tie breaks) then varies with it; after this it depends on the surface only.
void SortMeshByPosition(TriangleMesh& mesh);

// Removes every point whose position repeats an earlier point's exactly, with its normal and
// attributes; the first of each position stays, and the rest keep their order. Returns how many
// went. Why: exact repeats (a sensor's stuck pixel, a cloud merged twice, a hostile upload of
// one position a million times) tie every neighbour search at distance 0, which makes k-nearest
// queries scan them all. Cost: one parallel sort of n (key, index) pairs; the cloud is left
// untouched when nothing repeats.
size_t RemoveDuplicatePoints(PointCloud& cloud);

// Removes the points `remove` marks (one flag per point), with their normals and attributes;
// the others keep their order.
void RemovePoints(PointCloud& cloud, const std::vector<uint8_t>& remove);

// Appends `more`'s points and normals to `cloud`; of `cloud`'s attributes, those `more` has too
// (by name, one value per point) are appended, the others dropped, so that every attribute
// left covers every point.
void AppendCloud(PointCloud& cloud, const PointCloud& more);

// Finds a non-finite coordinate; returns the index of the first bad point or -1.
int64_t FindNonFinite(std::span<const Vec3f> points);

}  // namespace lsqsurf::core
