#include "worker/io/mesh_part.h"

#include <algorithm>
#include <bit>

#include "absl/container/flat_hash_map.h"
#include "worker/core/binary.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::io {
namespace {

constexpr char kMagic[] = "LQM1";
static_assert(std::endian::native == std::endian::little, "LQM1 is little-endian, as the machine's order");

absl::Status Bad(std::string_view what) { return absl::InvalidArgumentError(core::StrCat("mesh part: ", what)); }

}  // namespace

std::string EncodeMeshPart(int64_t first_vertex, std::span<const core::Vec3f> vertices,
                           std::span<const core::Vec3f> normals, std::span<const core::ScalarAttribute> attributes,
                           std::span<const std::array<int64_t, 3>> faces) {
  core::BinaryWriter out;
  for (int i = 0; i < 4; ++i) out.Scalar(kMagic[i]);
  out.Scalar(first_vertex);
  out.Array(vertices);
  out.Array(normals);
  out.Scalar<uint64_t>(attributes.size());
  for (const core::ScalarAttribute& a : attributes) {
    out.Text(a.name);
    out.Array(std::span<const float>(a.values));
  }
  out.Array(faces);
  return out.Take();
}

absl::StatusOr<MeshPart> DecodeMeshPart(std::string_view bytes) {
  if (!bytes.starts_with(std::string_view(kMagic, 4))) return Bad("not an LQM1 part");
  core::BinaryReader in(bytes.substr(4));
  MeshPart part;
  if (!in.Scalar(part.first_vertex) || part.first_vertex < 0) return Bad("bad first vertex");
  if (!in.Array(part.vertices)) return Bad("truncated positions");
  if (!in.Array(part.normals) || (!part.normals.empty() && part.normals.size() != part.vertices.size())) {
    return Bad("the normals do not match the positions");
  }
  uint64_t attributes = 0;
  if (!in.Scalar(attributes) || attributes > 1024) return Bad("bad attribute count");
  part.attributes.resize(attributes);
  for (core::ScalarAttribute& a : part.attributes) {
    if (!in.Text(a.name) || !in.Array(a.values, part.vertices.size())) {
      return Bad("an attribute is truncated or does not match the positions");
    }
  }
  if (!in.Array(part.faces) || !in.AtEnd()) return Bad("truncated faces, or bytes after them");
  const int64_t end = part.first_vertex + static_cast<int64_t>(part.vertices.size());
  for (size_t f = 0; f < part.faces.size(); ++f) {
    for (const int64_t v : part.faces[f]) {
      if (v < 0 || v >= end) return Bad(core::StrCat("face ", f, " names vertex ", v, " of ", end));
    }
  }
  return part;
}

absl::Status SelfContainedParts::Remember(const MeshPart& part) {
  const int64_t p = parts_;
  if (part.first_vertex != vertices()) {
    return absl::InvalidArgumentError(core::StrCat("mesh part ", p, " starts at vertex ", part.first_vertex,
                                                   "; the parts before it hold ", vertices()));
  }
  if (p == 0) {
    normals_ = !part.normals.empty();
    for (const core::ScalarAttribute& a : part.attributes) {
      if (!wanted_ || std::find(wanted_->begin(), wanted_->end(), a.name) != wanted_->end()) names_.push_back(a.name);
    }
    values_.resize(names_.size());
  }
  if (normals_ != !part.normals.empty()) {
    return absl::InvalidArgumentError(
        core::StrCat("mesh part ", p, (normals_ ? " lacks" : " has"), " normals and part 0 does not"));
  }
  in_part_.assign(names_.size(), nullptr);
  for (size_t k = 0; k < names_.size(); ++k) {
    for (const core::ScalarAttribute& a : part.attributes) {
      if (a.name == names_[k]) in_part_[k] = &a;
    }
    if (in_part_[k] == nullptr) {
      return absl::InvalidArgumentError(core::StrCat("mesh part ", p, " lacks the attribute '", names_[k], "'"));
    }
  }
  ++parts_;
  positions_.insert(positions_.end(), part.vertices.begin(), part.vertices.end());
  normals_seen_.insert(normals_seen_.end(), part.normals.begin(), part.normals.end());
  for (size_t k = 0; k < names_.size(); ++k) {
    values_[k].insert(values_[k].end(), in_part_[k]->values.begin(), in_part_[k]->values.end());
  }
  return absl::OkStatus();
}

absl::StatusOr<core::TriangleMesh> SelfContainedParts::Next(const MeshPart& part) {
  if (vertices() + static_cast<int64_t>(part.vertices.size()) > int64_t{UINT32_MAX}) {
    return absl::ResourceExhaustedError("the mesh has more than 2^32 vertices");
  }
  LSQSURF_RETURN_IF_ERROR(Remember(part));
  core::TriangleMesh piece;
  const auto own = static_cast<int64_t>(part.vertices.size());
  std::vector<int64_t> borrowed;
  absl::flat_hash_map<int64_t, uint32_t> local;
  piece.faces.reserve(part.faces.size());
  for (const auto& face : part.faces) {
    core::Triangle t;
    for (int c = 0; c < 3; ++c) {
      const int64_t v = face[c];
      if (v >= part.first_vertex) {
        t[c] = static_cast<uint32_t>(v - part.first_vertex);
        continue;
      }
      const auto [it, added] = local.try_emplace(v, static_cast<uint32_t>(own + static_cast<int64_t>(borrowed.size())));
      if (added) borrowed.push_back(v);
      t[c] = it->second;
    }
    piece.faces.push_back(t);
  }
  piece.vertices = part.vertices;
  piece.normals = part.normals;
  for (size_t k = 0; k < names_.size(); ++k) piece.vertex_attributes.push_back({names_[k], in_part_[k]->values});
  for (const int64_t v : borrowed) {
    const auto i = static_cast<size_t>(v);
    piece.vertices.push_back(positions_[i]);
    if (normals_) piece.normals.push_back(normals_seen_[i]);
    for (size_t k = 0; k < names_.size(); ++k) piece.vertex_attributes[k].values.push_back(values_[k][i]);
  }
  return piece;
}

}  // namespace lsqsurf::io
