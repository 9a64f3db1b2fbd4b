#include "worker/io/mesh_part.h"

#include <bit>

#include "worker/core/binary.h"
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

}  // namespace lsqsurf::io
