#include <Eigen/Eigenvalues>
#include <algorithm>
#include <chrono>
#include <cmath>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/mesh_metrics.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/extract/j1a.h"
#include "worker/extract/j1a_isosurface.h"
#include "worker/extract/stitch.h"
#include "worker/extract/thin_walls.h"
#include "worker/pu/pu_internal.h"

namespace lsqsurf::pu {

namespace {

// Around the data, extraction cells are at most 2^this times the finest (8×: 40 spacings by
// default) where the surface is flat; one level more changed nothing on the bench shapes.
constexpr int kCoarseExtractionLevels = 3;

int ExtractionDepth(double root_edge, double target) {
  return std::clamp(static_cast<int>(std::lround(std::log2(root_edge / target))), 2,
                    extract::AdaptiveOctree::kMaxDepth);
}

// Whether the box of half-size `reach` around `centre` meets `region`.
bool BoxMeetsRegion(const Vec3d& centre, const Vec3d& reach, const core::Box3& region) {
  return !(((centre + reach).array() < region.min().array()).any() ||
           ((centre - reach).array() > region.max().array()).any());
}

// Adds the keys of the cells of `level` that the box of half-size `reach` around `centre` meets.
void AddCellsInBox(const extract::AdaptiveOctree& tree, int level, const Vec3d& centre, const Vec3d& reach,
                   absl::flat_hash_set<uint64_t>& cells) {
  const extract::OctreeCell lo = tree.CellAt(level, centre - reach), hi = tree.CellAt(level, centre + reach);
  for (uint32_t z = lo.z; z <= hi.z; ++z)
    for (uint32_t y = lo.y; y <= hi.y; ++y)
      for (uint32_t x = lo.x; x <= hi.x; ++x) cells.insert(extract::CellKey({level, x, y, z}));
}

// The extraction cells of levels [from, to) that a sharp fit's support meets: creases go to the
// finest cells, where the crease splitting places them (their curvature is not a chord's).
absl::flat_hash_set<uint64_t> CellsNearSharpFits(const PuFunction::Impl& impl, const extract::AdaptiveOctree& tree,
                                                 int from, int to, const core::Box3* region) {
  absl::flat_hash_set<uint64_t> cells;
  for (const LocalFit& fit : impl.fits) {
    if (fit.feature == Feature::kSmooth) continue;
    const Vec3d reach = Vec3d::Constant(fit.support_radius);
    if (region != nullptr && !BoxMeetsRegion(fit.centre, reach, *region)) continue;
    for (int level = from; level < to; ++level) AddCellsInBox(tree, level, fit.centre, reach, cells);
  }
  return cells;
}

// Corners and acute creases get leaves this many levels finer than `cell_size`, within
// kFineReach finest leaves of the point where a corner fit's sheets meet or of the line where an
// acute edge fit's two sheets do: the crease splits and corner points cut from the leaves'
// tetrahedra leave chords across the creases there (1.3e-3 of the diagonal on a 12-face hull at
// 200k points; the tips of a 50° edge cut up to 1.5 leaves deep), which halve with the leaf.
constexpr int kFineExtraLevels = 1;
constexpr double kFineReach = 2.0;
// Thin walls get as many more levels as their thickness asks for, up to this many.
constexpr int kMaxFineLevels = 3;
// An edge fit's crease gets them where its sheets' normals are 101.5° to 150° apart. Up to there
// the crease splits reach the crease (it lies at most 0.61 of a chord beyond it; a 96° edge of the
// smooth spot model made a second extraction there for nothing), and the tips of sharper ridges
// are so thin that finer leaves catch them here and there along the ridge (a 20° ridge at 200k
// points came out with Euler characteristic -4, where a closed surface has 2).
constexpr double kAcuteCosine = -0.2, kSharpestCosine = -0.866;

// Where the tangent planes of a corner fit's sheets meet (least squares), when their normals span
// all three directions (a 20° wedge's tip: smallest eigenvalue of Σnnᵀ 0.03 of the largest).
std::optional<Vec3d> CornerPointOf(const SharpFit& fit) {
  constexpr double kMinSpread = 0.01;
  Eigen::Matrix3d normal_moments = Eigen::Matrix3d::Zero();
  Vec3d offsets = Vec3d::Zero();
  for (int k = 0; k < fit.count; ++k) {
    const Sheet& sheet = fit.sheets[static_cast<size_t>(k)];
    normal_moments += sheet.normal * sheet.normal.transpose();
    offsets += sheet.normal * (sheet.normal.dot(sheet.origin) + sheet.height.coefficients[0]);
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> spread(normal_moments, Eigen::EigenvaluesOnly);
  if (!(spread.eigenvalues()(0) > kMinSpread * spread.eigenvalues()(2))) return std::nullopt;
  return normal_moments.ldlt().solve(offsets);
}

// Where the leaves are finer: a stretch of crease from `from` to `to`, a corner (one point), or a
// ball of radius `extent` about `from` (a thin wall).
struct FineZone {
  Vec3d from, to;
  bool corner = false;
  double extent = 0;
  int levels = kFineExtraLevels;  // Finer than the leaves of `cell_size`.

  double Distance(const Vec3d& x) const {
    const Vec3d d = to - from;
    const double length2 = d.squaredNorm();
    const double t = length2 > 0 ? std::clamp((x - from).dot(d) / length2, 0.0, 1.0) : 0.0;
    return std::max(0.0, (x - (from + t * d)).norm() - extent);
  }
  core::Box3 Bounds() const {
    core::Box3 box(from - Vec3d::Constant(extent));
    box.extend(to + Vec3d::Constant(extent));
    return box;
  }
};

// A wall (two sheets of one fit facing apart by more than 162°) thinner than kWallLeafShare of a
// leaf of `cell_size` gets, over its fit's support, leaves fine enough that it is that share of one
// thick: lattice edges that cross it with both ends outside miss it, and holes open through it. A
// plate 1.44e-3 thick turned off the axes, at 200k points (leaves 3.4e-3): Euler characteristic
// -2248, closed with leaves of 1.7e-3; a smaller one as densely sampled (leaves 4.7e-3): -698 with
// leaves of 2.3e-3, closed with 1.2e-3.
using extract::kWallFacingCosine;
using extract::kWallLeafShare;

// The wall zone of a sharp fit (edge or corner) two of whose sheets face apart and lie closer than
// kWallLeafShare leaves of `finest_edge` to each other at its centre.
std::optional<FineZone> WallZoneOf(const LocalFit& fit, const SharpFit& sharp, double finest_edge) {
  double thickness = std::numeric_limits<double>::infinity();
  for (int i = 0; i < sharp.count; ++i) {
    for (int j = i + 1; j < sharp.count; ++j) {
      const Sheet &a = sharp.sheets[static_cast<size_t>(i)], &b = sharp.sheets[static_cast<size_t>(j)];
      if (!(a.normal.dot(b.normal) < kWallFacingCosine)) continue;
      // Both sheets are signed distances near their planes, so their sum is minus the thickness.
      const double between = -(a.Evaluate(fit.centre, nullptr) + b.Evaluate(fit.centre, nullptr));
      if (between > 0) thickness = std::min(thickness, between);
    }
  }
  if (!(thickness < kWallLeafShare * finest_edge)) return std::nullopt;
  FineZone zone{fit.centre, fit.centre, true, fit.support_radius};
  zone.levels =
      std::min(kMaxFineLevels, static_cast<int>(std::ceil(std::log2(finest_edge * kWallLeafShare / thickness))));
  return zone;
}

// The stretch of an edge fit's crease (its two sheets' tangent planes' common line) inside the
// fit's support, if any, where its sheets' normals are 101.5° to 150° apart (an acute crease) or,
// with `ridge`, more (the finer leaves leave those out).
std::optional<FineZone> CreaseZoneOf(const LocalFit& fit, const SharpFit& sharp, bool ridge = false) {
  if (sharp.count != 2) return std::nullopt;
  const Sheet &a = sharp.sheets[0], &b = sharp.sheets[1];
  const double c = a.normal.dot(b.normal);
  if (ridge ? !(c <= kSharpestCosine) : !(c < kAcuteCosine && c > kSharpestCosine)) return std::nullopt;
  // The common line's point nearest the fit's centre: x = centre + s na + t nb on both planes.
  const double ra = a.normal.dot(a.origin - fit.centre) + a.height.coefficients[0];
  const double rb = b.normal.dot(b.origin - fit.centre) + b.height.coefficients[0];
  const double det = 1 - c * c;
  const Vec3d nearest = fit.centre + ((ra - c * rb) / det) * a.normal + ((rb - c * ra) / det) * b.normal;
  const double off2 = (nearest - fit.centre).squaredNorm(), r2 = fit.support_radius * fit.support_radius;
  if (!(off2 < r2)) return std::nullopt;
  const Vec3d half = a.normal.cross(b.normal).normalized() * std::sqrt(r2 - off2);
  return FineZone{nearest - half, nearest + half, false};
}

// The fine zones of the corner fits (CornerPointOf, inside the fit's support) and, with
// `acute_creases`, of the acute edge fits, and the wall zones of the fits looked at (WallZoneOf);
// with `region`, those within `reach` of it.
std::vector<FineZone> FineZones(const PuFunction::Impl& impl, const core::Box3* region, double reach,
                                double finest_edge, bool acute_creases) {
  std::vector<FineZone> zones;
  for (const LocalFit& fit : impl.fits) {
    if (fit.feature == Feature::kSmooth || (fit.feature == Feature::kEdge && !acute_creases)) continue;
    const SharpFit& sharp = impl.sharp_fits[static_cast<size_t>(fit.sharp)];
    std::optional<FineZone> zone;
    if (fit.feature == Feature::kCorner) {
      const std::optional<Vec3d> corner = CornerPointOf(sharp);
      if (corner && (*corner - fit.centre).norm() <= fit.support_radius) zone = FineZone{*corner, *corner, true};
    } else {
      zone = CreaseZoneOf(fit, sharp);
    }
    if (!zone) zone = WallZoneOf(fit, sharp, finest_edge);
    if (!zone) continue;
    const core::Box3 box = zone->Bounds();
    if (region != nullptr && !BoxMeetsRegion(box.center(), box.sizes() / 2 + Vec3d::Constant(reach), *region)) continue;
    zones.push_back(*zone);
  }
  return zones;
}

// The creases of the edge fits sharper than the finer leaves go (CreaseZoneOf with `ridge`).
std::vector<FineZone> SharpRidges(const PuFunction::Impl& impl) {
  std::vector<FineZone> ridges;
  for (const LocalFit& fit : impl.fits) {
    if (fit.feature != Feature::kEdge) continue;
    if (auto zone = CreaseZoneOf(fit, impl.sharp_fits[static_cast<size_t>(fit.sharp)], true)) ridges.push_back(*zone);
  }
  return ridges;
}

// Adds the cells of `level` that the box of half-size `reach` about a corner meets, or whose
// centres lie within `reach` of a crease.
void AddCellsNearZone(const extract::AdaptiveOctree& tree, int level, const FineZone& zone, double reach,
                      absl::flat_hash_set<uint64_t>& cells) {
  if (zone.corner) return AddCellsInBox(tree, level, zone.from, Vec3d::Constant(reach + zone.extent), cells);
  const core::Box3 box = zone.Bounds();
  absl::flat_hash_set<uint64_t> in_box;
  AddCellsInBox(tree, level, box.center(), box.sizes() / 2 + Vec3d::Constant(reach), in_box);
  for (uint64_t key : in_box) {
    if (zone.Distance(tree.CellCentre(extract::CellFromKey(key))) <= reach) cells.insert(key);
  }
}

// Which fine zones an extraction tree refines (FineZone).
enum class FineLeaves { kNone, kCorners, kCornersAndAcuteCreases };

// Extract's J1a tree (2:1 balanced) and the finest cells that hold points (where tracking starts).
struct ExtractionTree {
  explicit ExtractionTree(const core::Box3& root, int depth) : tree(root, depth) {}
  extract::AdaptiveOctree tree;
  std::vector<extract::OctreeCell> start;
  std::vector<FineZone> fine_zones;  // Refined within fine_reach to their levels more.
  double fine_reach = 0;
  double finest_edge = 0;  // Of the leaves `cell_size` asks for.
};

// Extract's finest level (from `cell_size`) and the coarsest it allows around the data.
struct ExtractionLevels {
  int finest = 0;
  int band = 0;
};
ExtractionLevels LevelsAt(double root_edge, double mean_spacing, const PuExtractParams& params) {
  const int finest = ExtractionDepth(root_edge, params.cell_size * mean_spacing);
  return ExtractionLevels{finest, std::max(1, finest - kCoarseExtractionLevels)};
}

absl::StatusOr<ExtractionLevels> LevelsFor(const PuFunction& function, const PuExtractParams& params) {
  if (!(params.cell_size > 0) || !std::isfinite(params.cell_size)) {
    return absl::InvalidArgumentError("cell_size must be a positive number");
  }
  if (!(params.cell_size * function.stats().mean_spacing > 0)) {
    return absl::InvalidArgumentError("the points have no spacing to size cells by");
  }
  return LevelsAt(function.stats().root_edge, function.stats().mean_spacing, params);
}

// Balancing and the band's neighbours reach about two coarse cells; four keep the tree exact.
constexpr int kReachCoarseCells = 4;

// The finest extraction level comes from `cell_size`; around the data the tree is refined to at
// least kCoarseExtractionLevels levels above it, and finer where flat triangles would stray from
// the surface by more than `chord_error`, or where a sharp fit makes a crease. With `region`, only
// the points and sharp fits in that box are looked at: inside it, away from its sides by a few
// coarse cells, the tree is the whole one's (every decision is local).
absl::StatusOr<std::unique_ptr<ExtractionTree>> BuildExtractionTree(const PuFunction& function,
                                                                    const PuFunction::Impl& impl,
                                                                    const PuExtractParams& params,
                                                                    const core::Box3* region, core::JobContext& ctx,
                                                                    FineLeaves fine = FineLeaves::kCorners) {
  const auto levels = LevelsFor(function, params);
  if (!levels.ok()) return levels.status();
  const int depth = levels->finest, band_level = levels->band;
  // Every tree has room for the fine zones' leaves, so that vertex keys have one scale in every
  // tile and edit of a function, whether or not it has such zones there.
  const int corner_depth = std::min(depth + kMaxFineLevels, extract::AdaptiveOctree::kMaxDepth);
  auto built = std::make_unique<ExtractionTree>(core::Box3(impl.origin, impl.origin + Vec3d::Constant(impl.root_edge)),
                                                corner_depth);
  extract::AdaptiveOctree& tree = built->tree;
  std::vector<Vec3f> local_points;
  std::span<const Vec3f> points = impl.cloud->positions;
  if (region != nullptr) {
    for (const Vec3f& p : impl.cloud->positions) {
      if (region->contains(p.cast<double>())) local_points.push_back(p);
    }
    points = local_points;
  }
  extract::SurfaceBand band = extract::MarkSurfaceBand(tree, points, band_level);
  extract::SurfaceBand fine_band = extract::MarkSurfaceBand(tree, points, depth);
  band.occupied.clear();
  const double chord_bound = params.chord_error * impl.Diagonal();
  absl::flat_hash_set<uint64_t> crease_cells = CellsNearSharpFits(impl, tree, band_level, depth, region);
  // In the fine zones the band goes on to their levels: the points in the finest cells within
  // fine_reach of a zone mark the finer band there, at every level a zone near them asks for.
  absl::flat_hash_set<uint64_t> finer_start;
  built->finest_edge = tree.CellEdge(depth);
  built->fine_reach = kFineReach * tree.CellEdge(depth);
  if (corner_depth > depth && fine != FineLeaves::kNone) {
    built->fine_zones =
        FineZones(impl, region, built->fine_reach, built->finest_edge, fine == FineLeaves::kCornersAndAcuteCreases);
    // Per number of extra levels (index − 1): the cells near zones asking for it, and their points.
    std::vector<absl::flat_hash_set<uint64_t>> zone_cells(static_cast<size_t>(corner_depth - depth));
    std::vector<std::vector<Vec3f>> zone_points(zone_cells.size());
    for (const FineZone& zone : built->fine_zones) {
      const size_t at = static_cast<size_t>(std::min(zone.levels, corner_depth - depth) - 1);
      AddCellsNearZone(tree, depth, zone, built->fine_reach, zone_cells[at]);
    }
    if (std::any_of(zone_cells.begin(), zone_cells.end(), [](const auto& cells) { return !cells.empty(); })) {
      for (const Vec3f& p : points) {
        const uint64_t key = extract::CellKey(tree.CellAt(depth, p.cast<double>()));
        for (size_t at = 0; at < zone_cells.size(); ++at) {
          if (zone_cells[at].contains(key)) zone_points[at].push_back(p);
        }
      }
    }
    for (size_t at = 0; at < zone_cells.size(); ++at) {
      if (zone_cells[at].empty()) continue;
      const extract::SurfaceBand zone_band =
          extract::MarkSurfaceBand(tree, zone_points[at], depth + static_cast<int>(at) + 1);
      fine_band.ancestors.insert(zone_band.ancestors.begin(), zone_band.ancestors.end());
      finer_start.insert(zone_band.occupied.begin(), zone_band.occupied.end());
      crease_cells.insert(zone_cells[at].begin(), zone_cells[at].end());
    }
  }
  LSQSURF_RETURN_IF_ERROR(extract::RefineSurfaceBand(
      tree, band, band_level, fine_band,
      [&](const extract::OctreeCell& c) {
        // Below `depth` only the fine zones' cells are visited, and they want their levels.
        if (c.level > depth || crease_cells.contains(extract::CellKey(c))) return true;
        return extract::EstimateChordError(function, tree.CellCentre(c), tree.CellEdge(c.level)) > chord_bound;
      },
      ctx));
  band.ancestors.clear();
  fine_band.ancestors.clear();
  tree.Balance();
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  // A start cell split for a corner holds no leaf (LeafContaining skips it); its points' finer
  // cells start there instead.
  built->start.reserve(fine_band.occupied.size() + finer_start.size());
  for (uint64_t key : fine_band.occupied) built->start.push_back(extract::CellFromKey(key));
  for (uint64_t key : finer_start) built->start.push_back(extract::CellFromKey(key));
  return built;
}

// The finer leaves at a corner or an acute crease can catch its tip (a 20° ridge's end) beyond a
// neck that the leaves beside them miss: the tip comes out as a closed speck of its own. Such
// specks (smaller than a finest leaf, within `reach` of a zone) are dropped; the tip is then cut
// as it would be without the finer leaves. The leaves of `cell_size` do the same along ridges
// sharper than 30° (an 8-point hull's 28.6° edge at 100k points: three specks along it), so their
// creases are zones here too (SharpRidges, added to `refined`). Returns the specks dropped.
int64_t DropSpecksNearZones(const PuFunction::Impl& impl, std::span<const FineZone> refined, double reach,
                            double finest_edge, extract::IsosurfaceResult& result) {
  std::vector<FineZone> zones = SharpRidges(impl);
  zones.insert(zones.end(), refined.begin(), refined.end());
  if (zones.empty()) return 0;
  auto near_zone = [&](const core::Box3& box) {
    const double half_diagonal = core::Diagonal(box) / 2;
    return std::any_of(zones.begin(), zones.end(),
                       [&](const FineZone& zone) { return zone.Distance(box.center()) <= reach + half_diagonal; });
  };
  int64_t specks = 0;
  std::vector<char> keep = core::FacesOfComponents(
      result.mesh, [&](const core::Box3& box) { return core::Diagonal(box) < finest_edge && near_zone(box); }, specks);
  if (specks == 0) return 0;
  for (char& flag : keep) flag = !flag;  // The specks' faces were flagged.
  extract::KeepFaces(keep, result.mesh, result.trace);
  return specks;
}

// Adds the vertex attributes "depth", "degree" and "feature" (the dominant fit's) to `mesh`.
absl::Status LabelVertices(const PuFunction& function, core::TriangleMesh& mesh, core::JobContext& ctx) {
  core::ScalarAttribute depth_attribute{"depth", std::vector<float>(mesh.vertices.size())};
  core::ScalarAttribute degree_attribute{"degree", std::vector<float>(mesh.vertices.size())};
  core::ScalarAttribute feature_attribute{"feature", std::vector<float>(mesh.vertices.size())};
  LSQSURF_RETURN_IF_ERROR(core::ParallelFor(
      mesh.vertices.size(), 1024,
      [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i) {
          const FitLabel label = function.DominantFit(mesh.vertices[i].cast<double>());
          depth_attribute.values[i] = static_cast<float>(label.depth);
          degree_attribute.values[i] = static_cast<float>(label.degree);
          feature_attribute.values[i] = static_cast<float>(label.feature);
        }
      },
      &ctx));
  mesh.vertex_attributes.push_back(std::move(depth_attribute));
  mesh.vertex_attributes.push_back(std::move(degree_attribute));
  mesh.vertex_attributes.push_back(std::move(feature_attribute));
  return absl::OkStatus();
}

// The leaves of `tree` whose cube meets one of the balls: a descent from the root that carries the
// balls meeting each cell.
std::vector<extract::OctreeCell> LeavesMeetingBalls(const extract::AdaptiveOctree& tree,
                                                    std::span<const PuEditStats::Ball> balls) {
  auto meets = [&](const extract::OctreeCell& c, const PuEditStats::Ball& ball) {
    const double edge = tree.CellEdge(c.level);
    const Vec3d lo = tree.origin() + edge * Vec3d(c.x, c.y, c.z);
    const Vec3d nearest = ball.centre.cwiseMax(lo).cwiseMin(lo + Vec3d::Constant(edge));
    return (nearest - ball.centre).squaredNorm() <= ball.radius * ball.radius;
  };
  std::vector<extract::OctreeCell> leaves;
  std::vector<std::pair<extract::OctreeCell, std::vector<uint32_t>>> stack;
  std::vector<uint32_t> all(balls.size());
  for (uint32_t i = 0; i < all.size(); ++i) all[i] = i;
  stack.push_back({extract::OctreeCell{}, std::move(all)});
  while (!stack.empty()) {
    auto [cell, near] = std::move(stack.back());
    stack.pop_back();
    const extract::OctreeCell here = cell;  // Lambdas capture no structured binding before clang 16.
    std::erase_if(near, [&](uint32_t i) { return !meets(here, balls[i]); });
    if (near.empty()) continue;
    if (!tree.IsSubdivided(cell)) {
      if (tree.IsLeaf(cell)) leaves.push_back(cell);
      continue;
    }
    for (uint32_t k = 0; k < 8; ++k) {
      stack.push_back(
          {{cell.level + 1, 2 * cell.x + (k & 1), 2 * cell.y + ((k >> 1) & 1), 2 * cell.z + (k >> 2)}, near});
    }
  }
  return leaves;
}

bool SameExtraction(const PuExtractParams& a, const PuExtractParams& b) {
  const extract::MarchingOptions &x = a.marching, &y = b.marching;
  return a.cell_size == b.cell_size && a.chord_error == b.chord_error && a.label_vertices == b.label_vertices &&
         x.refine_steps == y.refine_steps && x.max_patch_triangles == y.max_patch_triangles &&
         x.crease_angle == y.crease_angle && x.snap_share == y.snap_share && x.relax_steps == y.relax_steps &&
         x.vertex_normals == y.vertex_normals;
}

// Only sharp fits make creases; without them there is nothing to split edges on.
extract::MarchingOptions MarchingFor(const PuFunction::Impl& impl, const PuExtractParams& params) {
  extract::MarchingOptions marching = params.marching;
  if (impl.sharp_fits.empty()) marching.crease_angle = 0;
  return marching;
}

// One extraction of the whole surface with the `fine` leaves; specks are dropped near its own
// fine zones, or near `speck_zones` where given (so that surfaces compared drop alike).
struct WholeExtraction {
  extract::IsosurfaceResult surface;
  std::vector<FineZone> zones;  // Those refined.
  double fine_reach = 0;        // ExtractionTree::fine_reach.
};
absl::StatusOr<WholeExtraction> ExtractWhole(const PuFunction& function, const PuExtractParams& params, FineLeaves fine,
                                             std::span<const FineZone> speck_zones, core::JobContext& ctx,
                                             bool close_pierced_edges = false) {
  const PuFunction::Impl& impl = function.impl();
  core::SubContext build_ctx(ctx, "building the J1a tree", 0.0, 0.1);
  const auto tree_start = std::chrono::steady_clock::now();
  auto built = BuildExtractionTree(function, impl, params, nullptr, build_ctx, fine);
  if (!built.ok()) return built.status();
  const double tree_seconds = core::SecondsSince(tree_start);
  core::SubContext extract_ctx(ctx, "extracting surface", 0.1, 1.0);
  extract::MarchingOptions marching = MarchingFor(impl, params);
  marching.close_pierced_edges = close_pierced_edges;
  auto surface = extract::ExtractIsosurfaceOnTree(function, (*built)->tree, (*built)->start, params.max_leaves,
                                                  marching, extract_ctx);
  if (!surface.ok()) return surface.status();
  WholeExtraction out{*std::move(surface), std::move((*built)->fine_zones), (*built)->fine_reach};
  out.surface.stats.tree_seconds = tree_seconds;
  const std::span<const FineZone> refined = speck_zones.empty() ? std::span<const FineZone>(out.zones) : speck_zones;
  out.surface.stats.corner_specks =
      DropSpecksNearZones(impl, refined, out.fine_reach, (*built)->finest_edge, out.surface);
  return out;
}

// Whether the finer leaves may have added to the topology: the surface's faces whose centroid lies
// within `reach` of a zone, welded by position, hold a handle (2C − χ − B is not 0, C their
// components, B their boundary loops; a band about a polytope's edges is a sphere with holes and
// has none) or a closed piece (a tip beyond a neck). Only those faces are looked at, so that a
// smooth scan with a few acute spots (a horn's tip) pays next to nothing.
bool TopologyNearZonesInDoubt(const core::TriangleMesh& mesh, std::span<const FineZone> zones, double reach) {
  // The zones meeting each cell of a grid of edge `reach`.
  auto cell_of = [&](const Vec3d& x) {
    const Eigen::Array3d c = (x / reach).array().floor();
    return std::array<int64_t, 3>{static_cast<int64_t>(c.x()), static_cast<int64_t>(c.y()),
                                  static_cast<int64_t>(c.z())};
  };
  absl::flat_hash_map<std::array<int64_t, 3>, std::vector<uint32_t>> zones_at;
  core::Box3 near;  // Of all zones, widened by `reach`: most faces of a scan are far from every one.
  for (uint32_t k = 0; k < zones.size(); ++k) {
    const core::Box3 box = zones[k].Bounds();
    near.extend(box.min() - Vec3d::Constant(reach)), near.extend(box.max() + Vec3d::Constant(reach));
    const auto lo = cell_of(box.min() - Vec3d::Constant(reach)), hi = cell_of(box.max() + Vec3d::Constant(reach));
    for (int64_t x = lo[0]; x <= hi[0]; ++x)
      for (int64_t y = lo[1]; y <= hi[1]; ++y)
        for (int64_t z = lo[2]; z <= hi[2]; ++z) zones_at[{x, y, z}].push_back(k);
  }
  core::TriangleMesh patch;
  absl::flat_hash_map<std::array<float, 3>, uint32_t> index_of;  // Welding by position.
  auto vertex = [&](uint32_t v) {
    const Vec3f& p = mesh.vertices[v];
    const auto [at, fresh] = index_of.try_emplace({p.x(), p.y(), p.z()}, static_cast<uint32_t>(patch.vertices.size()));
    if (fresh) patch.vertices.push_back(p);
    return at->second;
  };
  for (const core::Triangle& t : mesh.faces) {
    const Vec3d centroid =
        (mesh.vertices[t[0]].cast<double>() + mesh.vertices[t[1]].cast<double>() + mesh.vertices[t[2]].cast<double>()) /
        3;
    if (!near.contains(centroid)) continue;
    const auto at = zones_at.find(cell_of(centroid));
    if (at == zones_at.end() || std::none_of(at->second.begin(), at->second.end(),
                                             [&](uint32_t k) { return zones[k].Distance(centroid) <= reach; })) {
      continue;
    }
    patch.faces.push_back({vertex(t[0]), vertex(t[1]), vertex(t[2])});
  }
  const core::MeshTopology topology = core::AnalyzeTopology(patch);
  return topology.closed_components > 0 ||
         2 * topology.components - topology.euler_characteristic() - topology.boundary_loops != 0;
}

core::MeshTopology WeldedTopology(const core::TriangleMesh& mesh) {
  return core::AnalyzeTopology(core::WeldByPosition(mesh));
}

// Whether `a` has more components, handles or edges without two faces than `b` (both welded by
// position). Closing pierced edges can leave edges of four faces (an 8-point hull's 28.6° ridge
// at 200k points: three).
bool MoreTopology(const core::MeshTopology& a, const core::MeshTopology& b) {
  // Twice the handles over all components (2 × components − χ for closed ones).
  auto handles = [](const core::MeshTopology& t) { return 2 * t.components - t.euler_characteristic(); };
  auto open_edges = [](const core::MeshTopology& t) { return t.boundary_edges + t.non_manifold_edges; };
  return a.components > b.components || handles(a) > handles(b) || open_edges(a) > open_edges(b);
}

}  // namespace

double ExtractionReach(double root_edge, double mean_spacing, const PuExtractParams& params) {
  return kReachCoarseCells * std::ldexp(root_edge, -LevelsAt(root_edge, mean_spacing, params).band);
}

namespace {

// The faces of `marched` whose leaf's centre lies in `core` (half-open, so that every leaf has
// one owner), their vertices renumbered; `seam` flags the vertices on edges of one kept face.
extract::IsosurfaceResult KeepOwnedFaces(const extract::AdaptiveOctree& tree, const core::Box3& core,
                                         extract::IsosurfaceResult& marched, std::vector<char>& seam) {
  auto owned = [&](uint64_t key) {
    const Vec3d c = tree.CellCentre(extract::CellFromKey(key));
    return InHalfOpenBox(core, c);
  };
  const core::TriangleMesh& mesh = marched.mesh;
  extract::IsosurfaceResult kept;
  kept.stats = marched.stats;
  std::vector<uint32_t> renumber(mesh.vertices.size(), UINT32_MAX);
  absl::flat_hash_map<std::pair<uint32_t, uint32_t>, int> edge_faces;
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    if (!owned(marched.trace.face_cells[f])) continue;
    core::Triangle t = mesh.faces[f];
    for (uint32_t& v : t) {
      if (renumber[v] == UINT32_MAX) {
        renumber[v] = static_cast<uint32_t>(kept.mesh.vertices.size());
        kept.mesh.vertices.push_back(mesh.vertices[v]);
        if (!mesh.normals.empty()) kept.mesh.normals.push_back(mesh.normals[v]);
        kept.trace.vertex_edges.push_back(marched.trace.vertex_edges[v]);
      }
      v = renumber[v];
    }
    for (size_t k = 0; k < 3; ++k) {
      ++edge_faces[std::minmax(t[k], t[(k + 1) % 3])];
    }
    kept.mesh.faces.push_back(t);
    kept.trace.face_cells.push_back(marched.trace.face_cells[f]);
  }
  seam.assign(kept.mesh.vertices.size(), 0);
  for (const auto& [edge, count] : edge_faces) {
    if (count == 1) seam[edge.first] = seam[edge.second] = 1;
  }
  kept.stats.crossings = static_cast<int64_t>(kept.mesh.vertices.size());
  return kept;
}

}  // namespace

absl::StatusOr<TileSurface> ExtractTile(const PuFunction& function, const PuExtractParams& params,
                                        const core::Box3& core, core::JobContext& ctx) {
  const PuFunction::Impl& impl = function.impl();
  const double reach = ExtractionReach(impl.root_edge, function.stats().mean_spacing, params);
  const core::Box3 region(core.min() - Vec3d::Constant(reach), core.max() + Vec3d::Constant(reach));
  core::SubContext build_ctx(ctx, "building the tile's J1a tree", 0.0, 0.2);
  auto built = BuildExtractionTree(function, impl, params, &region, build_ctx, FineLeaves::kCornersAndAcuteCreases);
  if (!built.ok()) return built.status();
  TileSurface tile;
  if ((*built)->start.empty()) return tile;
  extract::MarchingOptions raw = params.marching;
  raw.trace = true;
  raw.relax_steps = 0;
  raw.crease_angle = 0;
  core::SubContext extract_ctx(ctx, "extracting the tile", 0.2, 0.7);
  // Marching is local: the faces in `core` need only the leaves there, plus a coarse cell for the
  // pinhole and speck rules, which judge clusters of a few leaves.
  const double context = reach / kReachCoarseCells;
  const core::Box3 marched_box(core.min() - Vec3d::Constant(context), core.max() + Vec3d::Constant(context));
  auto marched = extract::ExtractIsosurfaceOnTree(function, (*built)->tree, (*built)->start, params.max_leaves, raw,
                                                  extract_ctx, &marched_box);
  if (!marched.ok()) return marched.status();
  // Specks go as in ExtractWhole, judged on the marched surface, which holds every speck that
  // reaches into `core` whole (they are smaller than a finest leaf).
  marched->stats.corner_specks =
      DropSpecksNearZones(impl, (*built)->fine_zones, (*built)->fine_reach, (*built)->finest_edge, *marched);
  tile.surface = KeepOwnedFaces((*built)->tree, core, *marched, tile.seam);
  built->reset();
  *marched = {};
  core::SubContext finish_ctx(ctx, "finishing the tile", 0.7, 0.95);
  LSQSURF_RETURN_IF_ERROR(
      extract::FinishPatch(function, MarchingFor(impl, params), tile.surface, finish_ctx, tile.seam));
  tile.seam.resize(tile.surface.mesh.vertices.size(), 0);
  if (params.label_vertices) LSQSURF_RETURN_IF_ERROR(LabelVertices(function, tile.surface.mesh, ctx));
  return tile;
}

double FinestExtractionCell(const PuFunction& function, const PuExtractParams& params) {
  const double root_edge = function.stats().root_edge;
  return std::ldexp(root_edge, -ExtractionDepth(root_edge, params.cell_size * function.stats().mean_spacing));
}

absl::StatusOr<extract::IsosurfaceResult> Extract(const PuFunction& function, const PuExtractParams& params,
                                                  core::JobContext& ctx) {
  core::SubContext fine_ctx(ctx, "extracting surface", 0.0, 0.95);
  auto fine = ExtractWhole(function, params, FineLeaves::kCornersAndAcuteCreases, {}, fine_ctx);
  if (!fine.ok()) return fine.status();
  if (!fine->zones.empty()) {
    // The finer leaves can also catch a pointed corner's or an acute crease's tip here and there
    // and leave a handle (a 12-face hull at 100k points: Euler characteristic 0; a 20° ridge
    // refined along its length: -4). They must not add to the topology. Where the surface near the
    // fine zones is in doubt, it is compared with the surface without them (specks dropped alike):
    // where that has fewer components or handles, the corners' leaves alone are tried, and where
    // they add too, the surface without any is kept.
    const std::vector<FineZone> zones = fine->zones;
    constexpr double kPatchReach = 2;  // Of fine_reach: the finer leaves and the balancing around them.
    if (TopologyNearZonesInDoubt(fine->surface.mesh, zones, kPatchReach * fine->fine_reach)) {
      fine->surface.stats.topology_checks = 1;
      const core::MeshTopology topology = WeldedTopology(fine->surface.mesh);
      core::SubContext plain_ctx(ctx, "extracting surface without finer leaves", 0.0, 0.95);
      auto plain = ExtractWhole(function, params, FineLeaves::kNone, zones, plain_ctx);
      if (!plain.ok()) return plain.status();
      const core::MeshTopology plain_topology = WeldedTopology(plain->surface.mesh);
      if (MoreTopology(topology, plain_topology)) {
        const bool creases = std::any_of(zones.begin(), zones.end(), [](const FineZone& z) { return !z.corner; });
        const bool corners = std::any_of(zones.begin(), zones.end(), [](const FineZone& z) { return z.corner; });
        std::optional<WholeExtraction> kept;
        // First with the pierced lattice edges closed (extract::MarchingOptions::close_pierced_edges):
        // the 12-face hull's handle at 100k points was a tunnel along an edge that its pointed
        // four-face corner's tip passes through.
        core::SubContext pierced_ctx(ctx, "extracting surface with pierced edges closed", 0.0, 0.95);
        auto closed = ExtractWhole(function, params, FineLeaves::kCornersAndAcuteCreases, zones, pierced_ctx, true);
        if (!closed.ok()) return closed.status();
        const bool pierced_closed = !MoreTopology(WeldedTopology(closed->surface.mesh), plain_topology);
        if (pierced_closed) {
          kept = *std::move(closed);
        } else if (creases && corners) {
          core::SubContext corners_ctx(ctx, "extracting surface with finer corners only", 0.0, 0.95);
          auto at_corners = ExtractWhole(function, params, FineLeaves::kCorners, zones, corners_ctx);
          if (!at_corners.ok()) return at_corners.status();
          if (!MoreTopology(WeldedTopology(at_corners->surface.mesh), plain_topology)) {
            kept = *std::move(at_corners);
          }
        }
        if (!kept) {
          kept = *std::move(plain);
          kept->surface.stats.corners_left_coarse = corners ? 1 : 0;
        }
        if (!pierced_closed) kept->surface.stats.creases_left_coarse = creases ? 1 : 0;
        kept->surface.stats.topology_checks = 1;
        *fine = *std::move(kept);
      }
    }
  }
  if (params.max_hole_edges > 0 && !params.marching.trace) {
    extract::CloseSmallHoles(fine->surface, params.max_hole_edges);
  }
  if (!params.label_vertices) return std::move(fine->surface);
  LSQSURF_RETURN_IF_ERROR(LabelVertices(function, fine->surface.mesh, ctx));
  return std::move(fine->surface);
}

absl::StatusOr<extract::IsosurfaceResult> ExtractEdited(const PuFunction& before, const PuFunction& after,
                                                        const PuEditStats& edit_stats, KeptSurface kept,
                                                        const PuExtractParams& requested, core::JobContext& ctx) {
  const PuExtractParams& params = kept.params;
  if (!SameExtraction(params, requested)) {
    return absl::FailedPreconditionError("the kept surface was extracted with other parameters");
  }
  // A snapped corner's place depends on every tetrahedron around it, some beyond the patch.
  if (params.marching.snap_share > 0) {
    return absl::FailedPreconditionError("a kept surface with snapped corners is extracted whole");
  }
  const PuFunction::Impl& b = before.impl();
  if (edit_stats.changed.empty()) return absl::FailedPreconditionError("the edit names no changed region");
  const auto tree_start = std::chrono::steady_clock::now();
  if (const auto levels = LevelsFor(before, params); !levels.ok()) return levels.status();
  core::Box3 changed;
  for (const PuEditStats::Ball& ball : edit_stats.changed) {
    changed.extend(ball.centre - Vec3d::Constant(ball.radius));
    changed.extend(ball.centre + Vec3d::Constant(ball.radius));
  }
  const Vec3d margin = Vec3d::Constant(ExtractionReach(before.stats().root_edge, before.stats().mean_spacing, params));
  const core::Box3 region(changed.min() - margin, changed.max() + margin);
  core::SubContext build_ctx(ctx, "building the J1a tree near the edit", 0.0, 0.2);
  auto built = BuildExtractionTree(before, b, params, &region, build_ctx);
  if (!built.ok()) return built.status();
  const extract::AdaptiveOctree& tree = (*built)->tree;
  std::vector<extract::OctreeCell> leaves = LeavesMeetingBalls(tree, edit_stats.changed);
  absl::flat_hash_set<uint64_t> cells;
  for (const extract::OctreeCell& c : leaves) cells.insert(extract::CellKey(c));
  // Every kept face near the change must come from a leaf of this tree (else the tree is not the
  // one the kept surface was made on, and the join would not be exact).
  for (uint64_t key : kept.trace.face_cells) {
    if (cells.contains(key)) continue;
    const extract::OctreeCell c = extract::CellFromKey(key);
    const Vec3d centre = tree.CellCentre(c);
    if (changed.contains(centre) && !tree.IsLeaf(c)) {
      return absl::FailedPreconditionError("the kept surface was made on another tree");
    }
  }
  const double tree_seconds = core::SecondsSince(tree_start);
  core::SubContext march_ctx(ctx, "extracting the edited part", 0.2, 0.8);
  extract::MarchingOptions marching = MarchingFor(after.impl(), params);
  // The kept surface may have had them closed (Extract); a patch that has them closed where it had
  // not only moves the surface a little, one that has them open could bring a handle back.
  marching.close_pierced_edges = !after.impl().sharp_fits.empty();
  auto patch = extract::MarchLeaves(after, tree, leaves, marching, march_ctx);
  if (!patch.ok()) return patch.status();
  built->reset();
  auto join = extract::PatchJoin::Prepare(kept.mesh, kept.trace, cells, *patch);
  if (!join.ok()) return join.status();
  core::SubContext finish_ctx(ctx, "finishing the edited part", 0.8, 0.95);
  LSQSURF_RETURN_IF_ERROR(extract::FinishPatch(after, marching, *patch, finish_ctx, join->fixed()));
  if (!kept.mesh.vertex_attributes.empty()) LSQSURF_RETURN_IF_ERROR(LabelVertices(after, patch->mesh, ctx));
  // A join must not open a closed surface nor cut it in pieces where the edit removed no points:
  // beside a 50° edge (a pentagonal pyramid at 150k points, refit in a ball on a base edge) the
  // patch came out open and in two pieces. Then the whole surface is extracted instead.
  std::optional<core::MeshTopology> closed_before;
  if (edit_stats.points_removed == 0) {
    const core::MeshTopology before_topology = WeldedTopology(kept.mesh);
    if (before_topology.watertight()) closed_before = before_topology;
  }
  extract::IsosurfaceResult result;
  result.stats = patch->stats;
  result.stats.tree_seconds = tree_seconds;
  result.stats.replaced_faces = join->removed_faces();
  result.stats.seam_edges = join->seam_edges();
  result.mesh = join->Merge(std::move(kept.mesh), std::move(kept.trace), *patch, result.trace);
  if (closed_before) {
    const core::MeshTopology topology = WeldedTopology(result.mesh);
    if (!topology.watertight() || topology.components != closed_before->components) {
      return absl::FailedPreconditionError("the local join would leave the closed surface open or in pieces");
    }
  }
  return result;
}

}  // namespace lsqsurf::pu
