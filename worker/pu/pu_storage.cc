#include <algorithm>
#include <array>
#include <string_view>
#include <vector>

#include "worker/core/binary.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/pu/pu_internal.h"

namespace lsqsurf::pu {

namespace {

constexpr std::string_view kPuMagic = "LQPU0003";
// Functions kept before sharp fits had up to kMaxSheets sheets: read, and their fits widened.
constexpr std::string_view kFourSheetMagic = "LQPU0002";

// A sharp fit as kFourSheetMagic stored it: SharpFit's and Sheet's members then, in their order.
struct FourSheetSheet {
  Vec3d origin, tangent_u, tangent_v, normal;
  double scale;
  BivariatePolynomial height;
};
struct FourSheetFit {
  std::array<FourSheetSheet, 4> sheets;
  int count = 0;
  std::array<bool, 3> take_max{};
  Feature feature = Feature::kEdge;
};

bool ReadSharpFits(core::BinaryReader& r, bool four_sheets, std::vector<SharpFit>& fits) {
  if (!four_sheets) return r.Array(fits);
  std::vector<FourSheetFit> old;
  if (!r.Array(old)) return false;
  fits.resize(old.size());
  for (size_t i = 0; i < old.size(); ++i) {
    if (old[i].count < 2 || old[i].count > 4) return false;
    for (size_t k = 0; k < static_cast<size_t>(old[i].count); ++k) {
      const FourSheetSheet& from = old[i].sheets[k];
      Sheet& to = fits[i].sheets[k];
      if (from.height.degree < 0 || from.height.degree > 2) return false;
      to.origin = from.origin, to.tangent_u = from.tangent_u, to.tangent_v = from.tangent_v, to.normal = from.normal;
      to.scale = from.scale;
      to.height.degree = from.height.degree;
      std::copy_n(from.height.coefficients.begin(), TermCount(from.height.degree), to.height.coefficients.begin());
    }
    std::copy(old[i].take_max.begin(), old[i].take_max.end(), fits[i].take_max.begin());
    fits[i].count = old[i].count;
    fits[i].feature = old[i].feature;
  }
  return true;
}

// Structure checks of a read function: every index in range, so that evaluation cannot leave
// its arrays whatever the bytes were.
bool Consistent(const PuFunction::Impl& m) {
  const size_t nodes = m.nodes.size();
  if (nodes == 0 || m.fits.empty() || !(m.root_edge > 0) || !m.origin.allFinite()) return false;
  if (m.cloud->normals.size() != m.cloud->positions.size()) return false;
  if (m.coverage_check && m.cloud->local_spacing.size() != m.cloud->positions.size()) return false;
  for (size_t i = 0; i < nodes; ++i) {
    const Node& n = m.nodes[i];
    if (n.level < 0 || n.level > 30) return false;
    if (n.first_child >= 0 &&
        (static_cast<size_t>(n.first_child) <= i || static_cast<size_t>(n.first_child) + 8 > nodes))
      return false;
    if (n.fit >= 0 && static_cast<size_t>(n.fit) >= m.fits.size()) return false;
  }
  for (const LocalFit& f : m.fits) {
    const int highest = f.quadric ? kQuadricLabel : kMaxDegree;
    if (f.degree < 0 || f.degree > highest || !(f.support_radius > 0) || !(f.scale > 0)) return false;
    if (f.sharp >= 0 && static_cast<size_t>(f.sharp) >= m.sharp_fits.size()) return false;
  }
  for (const SharpFit& f : m.sharp_fits) {
    if (f.count < 2 || f.count > kMaxSheets) return false;
    // Read as bytes: a stored flag other than 0 or 1 is not a bool.
    std::array<uint8_t, sizeof(f.take_max)> flags;
    std::memcpy(flags.data(), f.take_max.data(), sizeof(f.take_max));
    for (uint8_t flag : flags) {
      if (flag > 1) return false;
    }
    for (int k = 0; k < f.count; ++k) {
      if (f.sheets[static_cast<size_t>(k)].height.degree < 0 || f.sheets[static_cast<size_t>(k)].height.degree > 2)
        return false;
    }
  }
  return true;
}

// A fit as bytes: its frame and only the coefficients its degree uses (most fits are of degree
// 1–2, so this stores about half of the fixed-size record).
int StoredTerms(const LocalFit& f) { return f.quadric ? 10 : TermCount(f.degree); }

void WriteFits(std::span<const LocalFit> fits, core::BinaryWriter& w) {
  w.Scalar<uint64_t>(fits.size());
  for (const LocalFit& f : fits) {
    for (const Vec3d* v : {&f.centre, &f.origin, &f.tangent_u, &f.tangent_v, &f.normal}) {
      w.Scalar(v->x()), w.Scalar(v->y()), w.Scalar(v->z());
    }
    w.Scalar(f.support_radius), w.Scalar(f.scale);
    w.Scalar(f.degree), w.Scalar(f.depth), w.Scalar<uint8_t>(f.quadric), w.Scalar(f.feature), w.Scalar(f.sharp);
    const int terms = std::clamp(StoredTerms(f), 0, kMaxTerms);
    for (int k = 0; k < terms; ++k) w.Scalar(f.coefficients[static_cast<size_t>(k)]);
  }
}

bool ReadFits(core::BinaryReader& r, std::vector<LocalFit>& fits) {
  uint64_t count = 0;
  if (!r.Scalar(count) || count > (uint64_t{1} << 32)) return false;
  fits.clear();
  fits.reserve(static_cast<size_t>(std::min<uint64_t>(count, 1 << 24)));
  for (uint64_t i = 0; i < count; ++i) {
    LocalFit f;
    for (Vec3d* v : {&f.centre, &f.origin, &f.tangent_u, &f.tangent_v, &f.normal}) {
      if (!r.Scalar(v->x()) || !r.Scalar(v->y()) || !r.Scalar(v->z())) return false;
    }
    uint8_t quadric = 0;
    if (!r.Scalar(f.support_radius) || !r.Scalar(f.scale) || !r.Scalar(f.degree) || !r.Scalar(f.depth) ||
        !r.Scalar(quadric) || !r.Scalar(f.feature) || !r.Scalar(f.sharp)) {
      return false;
    }
    f.quadric = quadric != 0;
    const int terms = StoredTerms(f);
    if (terms < 0 || terms > kMaxTerms) return false;
    for (int k = 0; k < terms; ++k) {
      if (!r.Scalar(f.coefficients[static_cast<size_t>(k)])) return false;
    }
    fits.push_back(f);
  }
  return true;
}

}  // namespace

std::string SerializePu(const PuFunction& function) {
  const PuFunction::Impl& m = function.impl();
  const PuStats& st = m.stats;
  core::BinaryWriter w;
  w.Array<char>(std::span<const char>(kPuMagic.data(), kPuMagic.size()));
  w.Scalar(m.params);
  w.Scalar<uint8_t>(m.coverage_check);
  w.Scalar(m.coverage_factor);
  w.Scalar(m.origin.x()), w.Scalar(m.origin.y()), w.Scalar(m.origin.z());
  w.Scalar(m.root_edge);
  w.Scalar(m.deepest_level);
  for (double v : {st.root_edge, st.mean_spacing, st.noise_estimate, st.error_threshold}) w.Scalar(v);
  w.Scalar(st.min_points);
  w.Array<Vec3f>(m.cloud->positions);
  w.Array<Vec3f>(m.cloud->normals);
  w.Array<float>(m.cloud->local_spacing);
  w.Array<Node>(m.nodes);
  WriteFits(m.fits, w);
  w.Array<SharpFit>(m.sharp_fits);
  return w.Take();
}

bool IsStoredPu(std::string_view bytes) {
  if (bytes.size() < 8 + kPuMagic.size()) return false;
  const std::string_view magic = bytes.substr(8, kPuMagic.size());
  return magic == kPuMagic || magic == kFourSheetMagic;
}

absl::StatusOr<std::unique_ptr<PuFunction>> DeserializePu(std::string_view bytes) {
  auto bad = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("the stored PU function is unreadable: ", why));
  };
  core::BinaryReader r(bytes);
  std::vector<char> magic;
  if (!r.Array(magic)) return bad("wrong header");
  const std::string_view header(magic.data(), magic.size());
  if (header != kPuMagic && header != kFourSheetMagic) return bad("wrong header");
  auto read = std::make_unique<PuFunction::Impl>();
  PuFunction::Impl& m = *read;
  PuStats& st = m.stats;
  uint8_t coverage = 0;
  if (!r.Scalar(m.params) || !r.Scalar(coverage) || !r.Scalar(m.coverage_factor) || !r.Scalar(m.origin.x()) ||
      !r.Scalar(m.origin.y()) || !r.Scalar(m.origin.z()) || !r.Scalar(m.root_edge) || !r.Scalar(m.deepest_level) ||
      !r.Scalar(st.root_edge) || !r.Scalar(st.mean_spacing) || !r.Scalar(st.noise_estimate) ||
      !r.Scalar(st.error_threshold) || !r.Scalar(st.min_points)) {
    return bad("header fields");
  }
  m.coverage_check = coverage != 0;
  if (!r.Array(m.cloud->positions) || m.cloud->positions.size() < 4 ||
      !r.Array(m.cloud->normals, m.cloud->positions.size()) || !r.Array(m.cloud->local_spacing)) {
    return bad("points");
  }
  if (!r.Array(m.nodes) || !ReadFits(r, m.fits) || !ReadSharpFits(r, header == kFourSheetMagic, m.sharp_fits) ||
      !r.AtEnd())
    return bad("fits");
  if (!Consistent(m)) return bad("inconsistent structure");
  m.cloud->kd_tree = std::make_unique<core::KdTree>(m.cloud->positions);
  core::LocalJobContext ctx;
  LSQSURF_RETURN_IF_ERROR(IndexInfluence(m, ctx));
  return std::make_unique<PuFunction>(std::move(read));
}

namespace {

// 0002: vertex keys on a lattice one level finer (the extraction tree's room for corners).
constexpr std::string_view kSurfaceMagic = "LQSF0002";

}  // namespace

// The extraction parameters a kept surface records, field by field (no padding bytes stored).
void WriteExtractParams(const PuExtractParams& p, core::BinaryWriter& w) {
  w.Scalar(p.cell_size), w.Scalar(p.chord_error), w.Scalar(p.max_leaves), w.Scalar<uint8_t>(p.label_vertices);
  const extract::MarchingOptions& m = p.marching;
  w.Scalar(m.refine_steps), w.Scalar<uint8_t>(m.vertex_normals), w.Scalar(m.max_patch_triangles);
  w.Scalar(m.crease_angle), w.Scalar(m.snap_share), w.Scalar(m.relax_steps);
}

bool ReadExtractParams(core::BinaryReader& r, PuExtractParams& p) {
  uint8_t label = 0, normals = 0;
  extract::MarchingOptions& m = p.marching;
  const bool ok = r.Scalar(p.cell_size) && r.Scalar(p.chord_error) && r.Scalar(p.max_leaves) && r.Scalar(label) &&
                  r.Scalar(m.refine_steps) && r.Scalar(normals) && r.Scalar(m.max_patch_triangles) &&
                  r.Scalar(m.crease_angle) && r.Scalar(m.snap_share) && r.Scalar(m.relax_steps);
  p.label_vertices = label != 0;
  m.vertex_normals = normals != 0;
  return ok && label <= 1 && normals <= 1;
}

void WriteMesh(const core::TriangleMesh& mesh, core::BinaryWriter& w) {
  w.Array<Vec3f>(mesh.vertices);
  w.Array<Vec3f>(mesh.normals);
  w.Array<core::Triangle>(mesh.faces);
  w.Scalar<uint64_t>(mesh.vertex_attributes.size());
  for (const core::ScalarAttribute& a : mesh.vertex_attributes) {
    w.Text(a.name);
    w.Array<float>(a.values);
  }
}

std::string_view ReadMesh(core::BinaryReader& r, core::TriangleMesh& mesh) {
  uint64_t attributes = 0;
  if (!r.Array(mesh.vertices) || !r.Array(mesh.normals) || !r.Array(mesh.faces) || !r.Scalar(attributes) ||
      attributes > 16) {
    return "mesh";
  }
  const size_t n = mesh.vertices.size();
  if (!mesh.normals.empty() && mesh.normals.size() != n) return "normals";
  for (uint64_t k = 0; k < attributes; ++k) {
    core::ScalarAttribute a;
    if (!r.Text(a.name) || !r.Array(a.values, n)) return "attributes";
    mesh.vertex_attributes.push_back(std::move(a));
  }
  for (const core::Triangle& t : mesh.faces) {
    if (t[0] >= n || t[1] >= n || t[2] >= n) return "a face index out of range";
  }
  return {};
}

std::string SerializeSurface(const core::TriangleMesh& mesh, const extract::SurfaceTrace& trace,
                             const PuExtractParams& params) {
  core::BinaryWriter w;
  w.Array<char>(std::span<const char>(kSurfaceMagic.data(), kSurfaceMagic.size()));
  WriteExtractParams(params, w);
  WriteMesh(mesh, w);
  w.Array<uint64_t>(trace.vertex_edges);
  w.Array<uint64_t>(trace.face_cells);
  return w.Take();
}

absl::StatusOr<KeptSurface> DeserializeSurface(std::string_view bytes) {
  auto bad = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("the kept surface is unreadable: ", why));
  };
  core::BinaryReader r(bytes);
  std::vector<char> magic;
  if (!r.Array(magic) || std::string_view(magic.data(), magic.size()) != kSurfaceMagic) return bad("wrong header");
  KeptSurface surface;
  core::TriangleMesh& mesh = surface.mesh;
  if (!ReadExtractParams(r, surface.params)) return bad("parameters");
  if (const std::string_view why = ReadMesh(r, mesh); !why.empty()) return bad(why);
  const size_t n = mesh.vertices.size();
  if (!r.Array(surface.trace.vertex_edges, n) || !r.Array(surface.trace.face_cells, mesh.faces.size()) || !r.AtEnd()) {
    return bad("trace");
  }
  return surface;
}

}  // namespace lsqsurf::pu
