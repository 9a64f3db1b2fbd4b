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

// A zlib stream inflated a window at a time, so that what it holds is the window, never the
// whole payload: a stream that inflates a thousandfold (as zlib allows) costs its window only.
class Inflater {
 public:
  explicit Inflater(std::string_view packed) {
    ok_ = inflateInit(&z_) == Z_OK;
    z_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(packed.data()));
    z_.avail_in = static_cast<uInt>(std::min<size_t>(packed.size(), UINT32_MAX));
  }
  ~Inflater() {
    if (ok_) inflateEnd(&z_);
  }
  Inflater(const Inflater&) = delete;
  Inflater& operator=(const Inflater&) = delete;

  // Appends up to `room` inflated bytes to `out`. Errors: kInvalidArgument (not a zlib stream, or
  // one cut short).
  absl::Status More(std::string& out, size_t room) {
    if (!ok_) return absl::InternalError("zlib could not start");
    if (ended_) return absl::OkStatus();
    const size_t start = out.size();
    out.resize(start + room);
    z_.next_out = reinterpret_cast<Bytef*>(out.data() + start);
    z_.avail_out = static_cast<uInt>(room);
    const int rc = inflate(&z_, Z_NO_FLUSH);
    out.resize(out.size() - z_.avail_out);
    if (rc == Z_STREAM_END) {
      ended_ = true;
    } else if (rc == Z_BUF_ERROR && z_.avail_in == 0) {
      return absl::InvalidArgumentError("the compressed bytes end before their stream does");
    } else if (rc != Z_OK && rc != Z_BUF_ERROR) {
      return absl::InvalidArgumentError(core::StrCat("zlib could not inflate it (code ", rc, ")"));
    }
    return absl::OkStatus();
  }
  bool ended() const { return ended_; }
  uint64_t total() const { return z_.total_out; }

 private:
  z_stream z_{};
  bool ok_ = false;
  bool ended_ = false;
};

// The inflated payload, read through a window that always holds at least one whole cell's
// worth of bytes ahead of `pos` (kMaxCellBytes) unless the stream has ended.
class PayloadReader {
 public:
  PayloadReader(std::string_view packed, uint64_t declared, uint64_t max_bytes)
      : inflater_(packed), declared_(declared), max_bytes_(max_bytes) {}

  absl::Status Fill() {
    while (window_.size() - pos_ < kMaxCellBytes && !inflater_.ended()) {
      window_.erase(0, pos_);
      pos_ = 0;
      LSQSURF_RETURN_IF_ERROR(inflater_.More(window_, kWindowBytes));
      if (inflater_.total() > declared_) {
        return absl::InvalidArgumentError(
            core::StrCat("it inflates to more than the ", declared_, " bytes its header declares"));
      }
      if (inflater_.total() > max_bytes_) {
        return absl::ResourceExhaustedError(core::StrCat("it inflates past ", max_bytes_,
                                                         " bytes, the most an upload may hold on this server or "
                                                         "under your quota (--max-upload-mib)"));
      }
    }
    return absl::OkStatus();
  }
  bool Varint(uint64_t& value) { return GetVarint(window_, pos_, value); }
  bool Byte(uint8_t& value) {
    if (pos_ >= window_.size()) return false;
    value = static_cast<uint8_t>(window_[pos_++]);
    return true;
  }
  // Whether the stream ended exactly where the last cell did, at its declared size.
  absl::Status CheckEnd() {
    LSQSURF_RETURN_IF_ERROR(Fill());
    if (pos_ != window_.size()) return absl::InvalidArgumentError("bytes follow the last cell");
    if (!inflater_.ended() || inflater_.total() != declared_) {
      return absl::InvalidArgumentError(
          core::StrCat("it inflates to ", inflater_.total(), " bytes where its header declares ", declared_));
    }
    return absl::OkStatus();
  }

 private:
  static constexpr size_t kWindowBytes = 64 << 10;
  Inflater inflater_;
  const uint64_t declared_, max_bytes_;
  std::string window_;
  size_t pos_ = 0;
};

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

absl::Status DecodeCellStream(std::string_view bytes, int64_t max_cells, uint64_t max_inflated_bytes,
                              core::VolumeMesh& mesh) {
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
  PayloadReader payload(bytes.substr(pos), payload_size, max_inflated_bytes);
  auto fill = [&]() -> absl::Status {
    absl::Status s = payload.Fill();
    if (s.ok() || s.code() == absl::StatusCode::kResourceExhausted) return s;
    return corrupt(std::string(s.message()));
  };
  LSQSURF_RETURN_IF_ERROR(fill());
  uint64_t count = 0;
  if (!payload.Varint(count)) return corrupt("no cell count");
  if (count > static_cast<uint64_t>(max_cells)) {
    return absl::ResourceExhaustedError(
        core::StrCat("the volume has ", count, " cells; this server accepts at most ", max_cells));
  }
  mesh.cell_types.clear();
  mesh.cell_vertices.clear();
  mesh.cell_offsets.assign(1, 0);
  int64_t previous = 0;
  for (uint64_t c = 0; c < count; ++c) {
    LSQSURF_RETURN_IF_ERROR(fill());
    uint8_t type = 0;
    if (!payload.Byte(type)) return corrupt(core::StrCat("it ends at cell ", c, " of ", count));
    const int n = core::CellVertexCount(type);
    if (n == 0) {
      return absl::InvalidArgumentError(core::StrCat("cell ", c, " is a ", core::CellTypeName(type),
                                                     "; volume meshes may hold tetrahedra, hexahedra, wedges and "
                                                     "pyramids only"));
    }
    for (int k = 0; k < n; ++k) {
      uint64_t z = 0;
      if (!payload.Varint(z)) return corrupt(core::StrCat("it ends inside cell ", c));
      const int64_t delta = static_cast<int64_t>(z >> 1) ^ -static_cast<int64_t>(z & 1);
      previous += delta;
      if (previous < 0 || previous > 0xffffffffLL) return corrupt(core::StrCat("cell ", c, " has a negative index"));
      mesh.cell_vertices.push_back(static_cast<uint32_t>(previous));
    }
    mesh.cell_types.push_back(type);
    mesh.cell_offsets.push_back(static_cast<uint32_t>(mesh.cell_vertices.size()));
  }
  if (absl::Status end = payload.CheckEnd(); !end.ok()) return corrupt(std::string(end.message()));
  if (count == 0) mesh.cell_offsets.clear();
  return absl::OkStatus();
}

}  // namespace lsqsurf::io
