// The steps of a tiled build that run apart from the planning: one tile's part of the surface
// (RunTile), the bytes plans and parts travel as, and the welding of the parts (TileJoiner).
#include <algorithm>
#include <cmath>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "worker/core/binary.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/pu/pu_internal.h"
#include "worker/pu/pu_tiles.h"
#include "worker/pu/tile_files.h"

namespace lsqsurf::pu {

namespace {

// kTileFormat rises with any change to these formats; the plan's magic carries it.
constexpr std::string_view kPlanMagic = "LQTP0004";
static_assert(kPlanMagic.back() - '0' == kTileFormat % 10);
constexpr std::string_view kTileMagic = "LQT10001";
constexpr std::string_view kPointsMagic = "LQTX0001";

bool ReadMagic(core::BinaryReader& r, std::string_view magic) {
  std::vector<char> read;
  return r.Array(read) && std::string_view(read.data(), read.size()) == magic;
}
void WriteMagic(core::BinaryWriter& w, std::string_view magic) {
  w.Array<char>(std::span<const char>(magic.data(), magic.size()));
}

void WriteVec(core::BinaryWriter& w, const core::Vec3d& v) { w.Scalar(v.x()), w.Scalar(v.y()), w.Scalar(v.z()); }
bool ReadVec(core::BinaryReader& r, core::Vec3d& v) { return r.Scalar(v.x()) && r.Scalar(v.y()) && r.Scalar(v.z()); }

// The frame's parameters field by field, so that equal plans are equal bytes (SameTilePlan).
static_assert(sizeof(PuParams) == 88, "a new PuParams field must travel in tile plans");
void WriteFitParams(core::BinaryWriter& w, const PuParams& p) {
  w.Scalar(p.error_threshold), w.Scalar(p.max_depth), w.Scalar(p.max_degree), w.Scalar(p.support_factor);
  w.Scalar(p.min_points), w.Scalar(p.max_normal_angle), w.Scalar<uint8_t>(p.coverage_check);
  w.Scalar(p.coverage_factor), w.Scalar<uint8_t>(p.orientation_check), w.Scalar(p.noise_level);
  w.Scalar<uint8_t>(p.sharp), w.Scalar(p.sharp_angle);
}
bool ReadFitParams(core::BinaryReader& r, PuParams& p) {
  uint8_t coverage = 0, orientation = 0, sharp = 0;
  const bool read = r.Scalar(p.error_threshold) && r.Scalar(p.max_depth) && r.Scalar(p.max_degree) &&
                    r.Scalar(p.support_factor) && r.Scalar(p.min_points) && r.Scalar(p.max_normal_angle) &&
                    r.Scalar(coverage) && r.Scalar(p.coverage_factor) && r.Scalar(orientation) &&
                    r.Scalar(p.noise_level) && r.Scalar(sharp) && r.Scalar(p.sharp_angle);
  p.coverage_check = coverage != 0, p.orientation_check = orientation != 0, p.sharp = sharp != 0;
  return read && coverage <= 1 && orientation <= 1 && sharp <= 1;
}

// The fit statistics a tile adds to the build's (the per-depth ones stay with the tile).
void WriteFitStats(core::BinaryWriter& w, const PuStats& s) {
  w.Scalar(s.fits_per_degree), w.Scalar(s.quadric_fits), w.Scalar(s.sharp_edges), w.Scalar(s.sharp_corners);
  w.Scalar(s.cells_examined), w.Scalar(s.unmet_threshold);
  w.Scalar(s.fit_seconds), w.Scalar(s.spacing_seconds), w.Scalar(s.index_seconds);
}
bool ReadFitStats(core::BinaryReader& r, PuStats& s) {
  return r.Scalar(s.fits_per_degree) && r.Scalar(s.quadric_fits) && r.Scalar(s.sharp_edges) &&
         r.Scalar(s.sharp_corners) && r.Scalar(s.cells_examined) && r.Scalar(s.unmet_threshold) &&
         r.Scalar(s.fit_seconds) && r.Scalar(s.spacing_seconds) && r.Scalar(s.index_seconds);
}

// One tile's part as RunTile makes it and TileJoiner reads it.
struct TilePart {
  uint64_t index = 0;
  int64_t points = 0;  // Read by the tile, its margin included.
  bool fitted = false;
  PuStats fit;
  TileSurface surface;  // No faces where the surface does not cross the tile.
};

std::string EncodeTilePart(const TilePart& part) {
  core::BinaryWriter w;
  WriteMagic(w, kTileMagic);
  w.Scalar(part.index), w.Scalar(part.points), w.Scalar<uint8_t>(part.fitted);
  WriteFitStats(w, part.fit);
  const extract::IsosurfaceResult& s = part.surface.surface;
  w.Scalar(s.stats);
  WriteMesh(s.mesh, w);
  w.Array<uint64_t>(s.trace.vertex_edges);
  w.Array<char>(part.surface.seam);
  return w.Take();
}

absl::StatusOr<TilePart> DecodeTilePart(std::string_view bytes) {
  auto bad = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("a tile's part is unreadable: ", why));
  };
  core::BinaryReader r(bytes);
  if (!ReadMagic(r, kTileMagic)) return bad("wrong header");
  TilePart part;
  uint8_t fitted = 0;
  if (!r.Scalar(part.index) || !r.Scalar(part.points) || !r.Scalar(fitted) || fitted > 1 ||
      !ReadFitStats(r, part.fit)) {
    return bad("statistics");
  }
  part.fitted = fitted != 0;
  extract::IsosurfaceResult& s = part.surface.surface;
  if (!r.Scalar(s.stats)) return bad("statistics");
  if (const std::string_view why = ReadMesh(r, s.mesh); !why.empty()) return bad(why);
  const size_t n = s.mesh.vertices.size();
  if (!r.Array(s.trace.vertex_edges, n) || !r.Array(part.surface.seam, n) || !r.AtEnd()) return bad("seam");
  return part;
}

// The faces of the welded surface so far that touch its open border (edges with one face: the
// seams still to be met and the holes), with their vertices' positions: what closing the whole
// surface's small holes looks at (extract::CloseSmallHoles), held while the tiles go by.
class OpenBorder {
 public:
  using Face = std::array<int64_t, 3>;

  // Adds a tile's faces (in the whole mesh's numbers) and its new vertices, numbered from `first`.
  void Add(std::span<const Face> faces, int64_t first, std::span<const core::Vec3f> vertices) {
    for (const Face& f : faces) {
      for (size_t k = 0; k < 3; ++k) {
        const int64_t a = f[k], b = f[(k + 1) % 3];
        // An edge run the other way by a face before meets it; otherwise it is open until one does.
        if (auto twin = open_.find({b, a}); twin != open_.end()) {
          if (--twin->second == 0) open_.erase(twin);
        } else {
          ++open_[{a, b}];
        }
      }
      for (int64_t v : f) {
        if (v >= first) positions_.try_emplace(v, vertices[static_cast<size_t>(v - first)]);
      }
      faces_.push_back(f);
    }
    Prune();
  }

  // Fills the holes into `fill` (whole-mesh numbers); returns how many were closed.
  int64_t CloseHoles(int max_edges, std::vector<Face>& fill) const {
    if (open_.empty() || max_edges < 3) return 0;
    extract::IsosurfaceResult border;
    absl::flat_hash_map<int64_t, uint32_t> local;
    std::vector<int64_t> global;
    auto number = [&](int64_t v) {
      const auto [it, fresh] = local.try_emplace(v, static_cast<uint32_t>(global.size()));
      if (fresh) global.push_back(v), border.mesh.vertices.push_back(positions_.at(v));
      return it->second;
    };
    for (const Face& f : faces_) {
      // A face at an earlier tile's vertex that had no open edge left (a fan met twice) is skipped.
      if (std::all_of(f.begin(), f.end(), [&](int64_t v) { return positions_.contains(v); })) {
        border.mesh.faces.push_back({number(f[0]), number(f[1]), number(f[2])});
      }
    }
    // Only loops of open edges are holes: the edges where the faces kept here end inside the
    // surface are not, and loops through their vertices stay as they are.
    absl::flat_hash_set<std::array<float, 3>> on_border;
    for (const auto& [edge, count] : open_) {
      for (int64_t v : {edge.first, edge.second}) {
        if (const auto p = positions_.find(v); p != positions_.end()) {
          on_border.insert({p->second.x(), p->second.y(), p->second.z()});
        }
      }
    }
    const size_t kept = border.mesh.faces.size();
    extract::CloseSmallHoles(border, max_edges, [&](const core::Vec3f& p) {
      return !on_border.contains({p.x(), p.y(), p.z()});
    });
    for (size_t f = kept; f < border.mesh.faces.size(); ++f) {
      const core::Triangle& t = border.mesh.faces[f];
      fill.push_back({global[t[0]], global[t[1]], global[t[2]]});
    }
    return border.stats.filled_holes;
  }

 private:
  // Keeps only the faces with a vertex on an open edge, and those vertices' positions.
  void Prune() {
    absl::flat_hash_set<int64_t> open_vertices;
    for (const auto& [edge, count] : open_) open_vertices.insert(edge.first), open_vertices.insert(edge.second);
    std::erase_if(faces_, [&](const Face& f) {
      return std::none_of(f.begin(), f.end(), [&](int64_t v) { return open_vertices.contains(v); });
    });
    absl::flat_hash_set<int64_t> used;
    for (const Face& f : faces_) used.insert(f.begin(), f.end());
    absl::erase_if(positions_, [&](const auto& entry) { return !used.contains(entry.first); });
  }

  absl::flat_hash_map<std::pair<int64_t, int64_t>, int> open_;  // Directed edges with no face back yet.
  std::vector<Face> faces_;
  absl::flat_hash_map<int64_t, core::Vec3f> positions_;
};

// Numbers a tile's vertices in the whole mesh, the border ones shared with the tiles before it
// (by lattice edge), and hands the tile to the sink.
class TileWelder {
 public:
  explicit TileWelder(SurfaceSink& sink) : sink_(sink) {}

  absl::Status Add(int64_t tile, const TileSurface& part) {
    const core::TriangleMesh& mesh = part.surface.mesh;
    std::vector<int64_t> number(mesh.vertices.size());
    vertices_.clear(), normals_.clear(), faces_.clear();
    attributes_.assign(mesh.vertex_attributes.size(), {});
    for (size_t a = 0; a < attributes_.size(); ++a) attributes_[a].name = mesh.vertex_attributes[a].name;
    const int64_t first = next_;
    for (size_t v = 0; v < mesh.vertices.size(); ++v) {
      const uint64_t edge = part.surface.trace.vertex_edges[v];
      if (part.seam[v] && edge != 0) {
        const auto [it, inserted] = seam_.try_emplace(edge, next_);
        if (!inserted) {
          number[v] = it->second;
          ++shared_;
          continue;
        }
      }
      number[v] = next_++;
      vertices_.push_back(mesh.vertices[v]);
      if (!mesh.normals.empty()) normals_.push_back(mesh.normals[v]);
      for (size_t a = 0; a < attributes_.size(); ++a) {
        attributes_[a].values.push_back(mesh.vertex_attributes[a].values[v]);
      }
    }
    for (const core::Triangle& t : mesh.faces) faces_.push_back({number[t[0]], number[t[1]], number[t[2]]});
    faces_total_ += static_cast<int64_t>(faces_.size());
    border_.Add(faces_, first, vertices_);
    return sink_.AddTile(TileOutput{tile, first, vertices_, normals_, attributes_, faces_});
  }

  // Closes the welded surface's holes of up to `max_edges` border edges, as a last part of faces
  // between the vertices already handed over. Returns the holes closed.
  absl::StatusOr<int64_t> CloseHoles(int64_t tile, int max_edges) {
    std::vector<std::array<int64_t, 3>> fill;
    const int64_t closed = border_.CloseHoles(max_edges, fill);
    if (fill.empty()) return closed;
    for (core::ScalarAttribute& a : attributes_) a.values.clear();
    faces_total_ += static_cast<int64_t>(fill.size());
    LSQSURF_RETURN_IF_ERROR(sink_.AddTile(TileOutput{tile, next_, {}, {}, attributes_, fill}));
    return closed;
  }
  int64_t shared() const { return shared_; }
  int64_t vertices() const { return next_; }
  int64_t faces() const { return faces_total_; }

 private:
  SurfaceSink& sink_;
  OpenBorder border_;
  absl::flat_hash_map<uint64_t, int64_t> seam_;
  int64_t next_ = 0, shared_ = 0, faces_total_ = 0;
  std::vector<core::Vec3f> vertices_, normals_;
  std::vector<core::ScalarAttribute> attributes_;
  std::vector<std::array<int64_t, 3>> faces_;
};

void AddStats(const extract::IsosurfaceStats& tile, extract::IsosurfaceStats& sum) {
  sum.cells_visited += tile.cells_visited;
  sum.surface_cells += tile.surface_cells;
  sum.field_evaluations += tile.field_evaluations;
  sum.tetrahedra += tile.tetrahedra;
  sum.crossings += tile.crossings;
  sum.rejected_polygons += tile.rejected_polygons;
  sum.restored_triangles += tile.restored_triangles;
  sum.crease_vertices += tile.crease_vertices;
  sum.crease_corners += tile.crease_corners;
  sum.snapped_corners += tile.snapped_corners;
  sum.relaxed_vertices += tile.relaxed_vertices;
  sum.flipped_edges += tile.flipped_edges;
  sum.tree_seconds += tile.tree_seconds;
  sum.tracking_seconds += tile.tracking_seconds;
  sum.marching_seconds += tile.marching_seconds;
  sum.crease_seconds += tile.crease_seconds;
  sum.relax_seconds += tile.relax_seconds;
}

void AddFitStats(const PuStats& tile, PuStats& sum) {
  for (size_t d = 0; d < sum.fits_per_degree.size(); ++d) sum.fits_per_degree[d] += tile.fits_per_degree[d];
  sum.quadric_fits += tile.quadric_fits;
  sum.sharp_edges += tile.sharp_edges;
  sum.sharp_corners += tile.sharp_corners;
  sum.cells_examined += tile.cells_examined;
  sum.unmet_threshold += tile.unmet_threshold;
  sum.fit_seconds += tile.fit_seconds;
  sum.spacing_seconds += tile.spacing_seconds;
  sum.index_seconds += tile.index_seconds;
}

}  // namespace

std::string EncodeTilePlan(const TilePlan& plan) {
  core::BinaryWriter w;
  WriteMagic(w, kPlanMagic);
  const PuFrame& f = plan.frame;
  WriteVec(w, f.origin);
  w.Scalar(f.root_edge), w.Scalar(f.diagonal), w.Scalar(f.mean_spacing), w.Scalar(f.noise_estimate);
  WriteFitParams(w, f.params);
  w.Scalar(f.max_support);
  WriteExtractParams(plan.extract, w);
  w.Scalar(plan.extract.max_hole_edges);  // Not in WriteExtractParams: kept surfaces do not store it.
  w.Scalar(plan.tile_level), w.Scalar(plan.data_margin), w.Scalar(plan.extraction_margin);
  w.Array<uint64_t>(plan.tiles);
  w.Scalar(plan.points), w.Scalar(plan.scratch_bytes);
  w.Scalar(plan.measure_seconds), w.Scalar(plan.scan_seconds), w.Scalar(plan.spacing_seconds);
  return w.Take();
}

absl::StatusOr<TilePlan> DecodeTilePlan(std::string_view bytes) {
  core::BinaryReader r(bytes);
  TilePlan plan;
  PuFrame& f = plan.frame;
  const bool read = ReadMagic(r, kPlanMagic) && ReadVec(r, f.origin) && r.Scalar(f.root_edge) && r.Scalar(f.diagonal) &&
                    r.Scalar(f.mean_spacing) && r.Scalar(f.noise_estimate) && ReadFitParams(r, f.params) &&
                    r.Scalar(f.max_support) && ReadExtractParams(r, plan.extract) &&
                    r.Scalar(plan.extract.max_hole_edges) && r.Scalar(plan.tile_level) && r.Scalar(plan.data_margin) &&
                    r.Scalar(plan.extraction_margin) && r.Array(plan.tiles) && r.Scalar(plan.points) &&
                    r.Scalar(plan.scratch_bytes) && r.Scalar(plan.measure_seconds) && r.Scalar(plan.scan_seconds) &&
                    r.Scalar(plan.spacing_seconds) && r.AtEnd();
  if (!read || !(f.root_edge > 0) || !f.origin.allFinite() || plan.tile_level < 0 || plan.tile_level > 20 ||
      !(f.max_support > 0) || !Validate(f.params).ok() || !PuExtractParamTable().Validate(plan.extract).ok() ||
      plan.extract.max_hole_edges < 0) {
    return absl::InvalidArgumentError("a tile plan is unreadable");
  }
  return plan;
}

bool SameTilePlan(std::string_view a, std::string_view b) {
  auto x = DecodeTilePlan(a), y = DecodeTilePlan(b);
  if (!x.ok() || !y.ok()) return false;
  for (TilePlan* plan : {&*x, &*y}) plan->measure_seconds = plan->scan_seconds = plan->spacing_seconds = 0;
  return EncodeTilePlan(*x) == EncodeTilePlan(*y);
}

std::string EncodeTilePoints(const core::PointCloud& points) {
  core::BinaryWriter w;
  WriteMagic(w, kPointsMagic);
  w.Array<core::Vec3f>(points.positions);
  w.Array<core::Vec3f>(points.normals);
  return w.Take();
}

absl::StatusOr<core::PointCloud> DecodeTilePoints(std::string_view bytes) {
  core::BinaryReader r(bytes);
  core::PointCloud points;
  if (!ReadMagic(r, kPointsMagic) || !r.Array(points.positions) || !r.Array(points.normals, points.positions.size()) ||
      !r.AtEnd()) {
    return absl::InvalidArgumentError("a tile's points are unreadable");
  }
  return points;
}

absl::StatusOr<std::string> RunTile(const TilePlan& plan, size_t index, core::PointCloud points,
                                    core::JobContext& ctx) {
  if (index >= plan.tiles.size()) {
    return absl::OutOfRangeError(core::StrCat("tile ", index, " of a plan of ", plan.tiles.size()));
  }
  TilePart part;
  part.index = index;
  part.points = static_cast<int64_t>(points.size());
  if (points.size() >= 4) {
    const TileGrid grid = TileGrid::AtLevel(plan.frame.origin, plan.frame.root_edge, plan.tile_level);
    const core::Box3 cube = grid.Cube(TileGrid::FromKey(plan.tiles[index]));
    const core::Vec3d reach = core::Vec3d::Constant(plan.extraction_margin);
    const core::Box3 region(cube.min() - reach, cube.max() + reach);
    core::SubContext fit_ctx(ctx, "fitting", 0.0, 0.5);
    auto function = BuildPuInFrame(points, plan.frame, &region, fit_ctx);
    if (!function.ok() && !absl::IsFailedPrecondition(function.status())) return function.status();
    points = {};          // The function holds what it needs of them.
    if (function.ok()) {  // Otherwise no fit is near it.
      part.fitted = true;
      part.fit = (*function)->stats();
      core::SubContext extract_ctx(ctx, "extracting", 0.5, 1.0);
      auto surface = ExtractTile(**function, plan.extract, cube, extract_ctx);
      if (!surface.ok()) return surface.status();
      part.surface = *std::move(surface);
    }
  }
  LSQSURF_RETURN_IF_ERROR(ctx.CheckCancelled());
  return EncodeTilePart(part);
}

struct TileJoiner::State {
  explicit State(const TilePlan& p, SurfaceSink& sink) : plan(p), welder(sink) {}
  const TilePlan& plan;
  TileWelder welder;
  TiledStats stats;
  size_t next = 0;
};

TileJoiner::TileJoiner(const TilePlan& plan, SurfaceSink& sink) : state_(std::make_unique<State>(plan, sink)) {}
TileJoiner::~TileJoiner() = default;
size_t TileJoiner::next_tile() const { return state_->next; }

absl::Status TileJoiner::Add(std::string_view tile) {
  auto part = DecodeTilePart(tile);
  if (!part.ok()) return part.status();
  State& st = *state_;
  if (part->index != st.next) {
    return absl::InvalidArgumentError(core::StrCat("tile ", part->index, " came where tile ", st.next, " belongs"));
  }
  ++st.next;
  TiledStats& s = st.stats;
  ++s.tiles_examined;
  if (part->points >= 4) s.largest_tile = std::max(s.largest_tile, part->points);
  if (part->fitted) AddFitStats(part->fit, s.fit);
  if (part->surface.surface.mesh.faces.empty()) return absl::OkStatus();
  AddStats(part->surface.surface.stats, s.extract);
  return st.welder.Add(s.tiles++, part->surface);
}

absl::StatusOr<TiledStats> TileJoiner::Finish() {
  State& st = *state_;
  const TilePlan& plan = st.plan;
  if (st.next != plan.tiles.size()) {
    return absl::FailedPreconditionError(
        core::StrCat("only ", st.next, " of the ", plan.tiles.size(), " tiles were joined"));
  }
  TiledStats& s = st.stats;
  s.frame = plan.frame;
  s.points = plan.points;
  s.tile_level = plan.tile_level;
  s.margin = plan.data_margin;
  s.scratch_bytes = plan.scratch_bytes;
  s.measure_seconds = plan.measure_seconds;
  s.scan_seconds = plan.scan_seconds;
  s.spacing_seconds = plan.spacing_seconds;
  s.seam_vertices = st.welder.shared();
  s.vertices = st.welder.vertices();
  s.faces = st.welder.faces();
  s.fit.mean_spacing = plan.frame.mean_spacing;
  s.fit.root_edge = plan.frame.root_edge;
  s.fit.noise_estimate = plan.frame.noise_estimate;
  s.fit.error_threshold = plan.frame.params.error_threshold;
  s.fit.min_points = plan.frame.params.min_points;
  if (s.faces == 0) return absl::FailedPreconditionError("no surface could be extracted from the tiles");
  auto closed = st.welder.CloseHoles(s.tiles, plan.extract.max_hole_edges);
  if (!closed.ok()) return closed.status();
  s.extract.filled_holes += *closed;
  s.faces = st.welder.faces();
  return s;
}

}  // namespace lsqsurf::pu
