#include "worker/io/volume_codec.h"

#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_codec.h"
#include "worker/io/varint.h"

namespace lsqsurf::io {
namespace {

constexpr std::string_view kCellMagic = "LQC1";
// The longest a cell can be in the payload: a type byte and 8 indices of at most 5 bytes each.
constexpr uint64_t kMaxCellBytes = 1 + 8 * 5;

// Inflates a zlib stream that must give exactly `expected` bytes. The output grows with what
// actually inflates (never allocated at the declared size up front), so a stream that merely
// declares a large size costs nothing.
absl::StatusOr<std::string> Inflate(std::string_view packed, uint64_t expected) {
  z_stream z{};
  if (inflateInit(&z) != Z_OK) return absl::InternalError("zlib could not start");
  struct End {
    z_stream& z;
    ~End() { inflateEnd(&z); }
  } end{z};
  std::string out;
  z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(packed.data()));
  z.avail_in = static_cast<uInt>(std::min<size_t>(packed.size(), UINT32_MAX));
  int rc = Z_OK;
  while (rc == Z_OK) {
    if (out.size() == z.total_out) {
      if (out.size() > expected) break;
      // Doubling from 64 KiB, to one byte past the declared size (which tells a longer stream).
      out.resize(std::min<uint64_t>(std::max<size_t>(out.size() * 2, 64 << 10), expected + 1));
    }
    z.next_out = reinterpret_cast<Bytef*>(out.data() + z.total_out);
    z.avail_out = static_cast<uInt>(std::min<uint64_t>(out.size() - z.total_out, UINT32_MAX));
    rc = inflate(&z, Z_NO_FLUSH);
    if (rc == Z_BUF_ERROR && z.avail_out > 0) break;  // Input ran out before the stream's end.
    if (rc == Z_BUF_ERROR) rc = Z_OK;
  }
  if (z.total_out > expected) {
    return absl::InvalidArgumentError(
        core::StrCat("it inflates to more than the ", expected, " bytes its header declares"));
  }
  if (rc != Z_STREAM_END) return absl::InvalidArgumentError(core::StrCat("zlib could not inflate it (code ", rc, ")"));
  if (z.total_out != expected) {
    return absl::InvalidArgumentError(
        core::StrCat("it inflates to ", z.total_out, " bytes where its header declares ", expected));
  }
  out.resize(z.total_out);
  return out;
}

}  // namespace

absl::StatusOr<std::string> EncodeVolumeVertices(const core::VolumeMesh& mesh, std::span<const std::string> fields,
                                                 const VolumeCodecOptions& options) {
  if (mesh.vertex_count() == 0) return absl::InvalidArgumentError("the volume has no vertices");
  core::PointCloud cloud;
  cloud.positions = mesh.positions;
  for (const std::string& name : fields) {
    const core::VertexField* f = mesh.FindField(name);
    if (f == nullptr || f->components != 1) {
      return absl::InvalidArgumentError(
          core::StrCat("the volume has no scalar field '", name, "'; its fields: ", core::DescribeFields(mesh)));
    }
    for (size_t i = 0; i < f->values.size(); ++i) {
      if (!std::isfinite(f->values[i])) {
        return absl::InvalidArgumentError(core::StrCat("field '", name, "' is NaN or infinite at vertex ", i));
      }
    }
    cloud.attributes.push_back({name, f->values});
  }
  DracoOptions draco;
  draco.position_bits = options.position_bits;
  draco.attribute_bits = options.value_bits;
  draco.speed = 10;  // Sequential coding: the cells refer to the vertex order.
  return EncodeDracoPointCloud(cloud, draco);
}

absl::Status DecodeVolumeVertices(std::string_view bytes, core::VolumeMesh& mesh) {
  LSQSURF_ASSIGN_OR_RETURN(core::PointCloud cloud, DecodeDracoPointCloud(bytes));
  mesh.positions = std::move(cloud.positions);
  mesh.fields.clear();
  for (core::ScalarAttribute& a : cloud.attributes) mesh.fields.push_back({a.name, 1, std::move(a.values)});
  return absl::OkStatus();
}

std::string EncodeCellStream(const core::VolumeMesh& mesh) {
  std::string payload;
  PutVarint(payload, mesh.cell_count());
  int64_t previous = 0;
  for (size_t c = 0; c < mesh.cell_count(); ++c) {
    payload += static_cast<char>(mesh.cell_types[c]);
    for (uint32_t v : mesh.cell(c)) {
      const int64_t delta = static_cast<int64_t>(v) - previous;
      PutVarint(payload, (static_cast<uint64_t>(delta) << 1) ^ static_cast<uint64_t>(delta >> 63));
      previous = v;
    }
  }
  uLongf size = compressBound(static_cast<uLong>(payload.size()));
  std::string packed(size, '\0');
  compress2(reinterpret_cast<Bytef*>(packed.data()), &size, reinterpret_cast<const Bytef*>(payload.data()),
            static_cast<uLong>(payload.size()), 6);
  packed.resize(size);
  std::string out(kCellMagic);
  PutVarint(out, payload.size());
  return out + packed;
}

absl::Status DecodeCellStream(std::string_view bytes, int64_t max_cells, core::VolumeMesh& mesh) {
  auto corrupt = [](std::string_view why) {
    return absl::InvalidArgumentError(core::StrCat("the cell stream is corrupt: ", why));
  };
  if (!bytes.starts_with(kCellMagic)) return corrupt("it does not start with LQC1");
  size_t pos = kCellMagic.size();
  uint64_t payload_size = 0;
  if (!GetVarint(bytes, pos, payload_size)) return corrupt("truncated header");
  // Refuse before inflating: the declared size bounds the cell count from below.
  if (payload_size > static_cast<uint64_t>(std::max<int64_t>(max_cells, 0)) * kMaxCellBytes + 10) {
    return absl::ResourceExhaustedError(
        core::StrCat("the cell stream declares ", payload_size, " bytes, more than ", max_cells, " cells can need"));
  }
  // Nor can it exceed what its compressed bytes inflate to at zlib's best ratio (1032:1).
  const uint64_t compressed = bytes.size() - pos;
  if (payload_size > compressed * 1032 + 64) {
    return corrupt(
        core::StrCat("it declares ", payload_size, " bytes, more than its ", compressed, " compressed bytes can hold"));
  }
  auto payload = Inflate(bytes.substr(pos), payload_size);
  if (!payload.ok()) return corrupt(std::string(payload.status().message()));
  pos = 0;
  uint64_t count = 0;
  if (!GetVarint(*payload, pos, count)) return corrupt("no cell count");
  if (count > static_cast<uint64_t>(max_cells)) {
    return absl::ResourceExhaustedError(
        core::StrCat("the volume has ", count, " cells; this server accepts at most ", max_cells));
  }
  mesh.cell_types.clear();
  mesh.cell_vertices.clear();
  mesh.cell_offsets.assign(1, 0);
  int64_t previous = 0;
  for (uint64_t c = 0; c < count; ++c) {
    if (pos >= payload->size()) return corrupt(core::StrCat("it ends at cell ", c, " of ", count));
    const auto type = static_cast<uint8_t>((*payload)[pos++]);
    const int n = core::CellVertexCount(type);
    if (n == 0) {
      return absl::InvalidArgumentError(core::StrCat("cell ", c, " is a ", core::CellTypeName(type),
                                                     "; volume meshes may hold tetrahedra, hexahedra, wedges and "
                                                     "pyramids only"));
    }
    for (int k = 0; k < n; ++k) {
      uint64_t z = 0;
      if (!GetVarint(*payload, pos, z)) return corrupt(core::StrCat("it ends inside cell ", c));
      const int64_t delta = static_cast<int64_t>(z >> 1) ^ -static_cast<int64_t>(z & 1);
      previous += delta;
      if (previous < 0 || previous > 0xffffffffLL) return corrupt(core::StrCat("cell ", c, " has a negative index"));
      mesh.cell_vertices.push_back(static_cast<uint32_t>(previous));
    }
    mesh.cell_types.push_back(type);
    mesh.cell_offsets.push_back(static_cast<uint32_t>(mesh.cell_vertices.size()));
  }
  if (pos != payload->size()) return corrupt("bytes follow the last cell");
  if (count == 0) mesh.cell_offsets.clear();
  return absl::OkStatus();
}

}  // namespace lsqsurf::io
