#include "worker/io/draco_header.h"

#include <cstring>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/varint.h"

namespace lsqsurf::io {
namespace {

constexpr int kMaxMetadataDepth = 32;
constexpr uint16_t kMetadataFlag = 0x8000;
constexpr uint8_t kPointCloud = 0;
constexpr uint8_t kTriangleMesh = 1;
constexpr uint8_t kKdTreeMethod = 1;       // Point clouds: 0 sequential, 1 kd-tree.
constexpr uint8_t kEdgebreakerMethod = 1;  // Meshes: 0 sequential, 1 Edgebreaker.

// Little-endian reads that fail, rather than run past the end, on truncated data.
class ByteReader {
 public:
  explicit ByteReader(std::string_view bytes) : bytes_(bytes) {}

  size_t remaining() const { return bytes_.size() - pos_; }

  bool Skip(uint64_t n) {
    if (n > remaining()) return false;
    pos_ += static_cast<size_t>(n);
    return true;
  }
  bool U8(uint8_t& out) {
    if (remaining() < 1) return false;
    out = static_cast<uint8_t>(bytes_[pos_++]);
    return true;
  }
  bool U16(uint16_t& out) {
    uint8_t lo = 0, hi = 0;
    if (!U8(lo) || !U8(hi)) return false;
    out = static_cast<uint16_t>(lo | (hi << 8));
    return true;
  }
  bool I32(int32_t& out) {
    uint32_t v = 0;
    for (int i = 0; i < 4; ++i) {
      uint8_t b = 0;
      if (!U8(b)) return false;
      v |= static_cast<uint32_t>(b) << (8 * i);
    }
    std::memcpy(&out, &v, sizeof(out));
    return true;
  }
  // A count as Draco writes it: LEB128 whose value fits 32 bits.
  bool Varint(uint32_t& out) {
    uint64_t v = 0;
    if (!GetVarint(bytes_, pos_, v) || v > 0xffffffffu) return false;
    out = static_cast<uint32_t>(v);
    return true;
  }

 private:
  std::string_view bytes_;
  size_t pos_ = 0;
};

absl::Status Corrupt(std::string_view what) {
  return absl::InvalidArgumentError(core::StrCat("the Draco data is truncated or corrupt (", what, ")"));
}

// A metadata block: entries (name, sized value) and named sub-blocks, recursively.
absl::Status SkipMetadata(ByteReader& in, int depth) {
  if (depth > kMaxMetadataDepth) {
    return absl::InvalidArgumentError(
        core::StrCat("the Draco metadata is nested more than ", kMaxMetadataDepth, " levels deep"));
  }
  uint32_t entries = 0;
  if (!in.Varint(entries)) return Corrupt("metadata entry count");
  for (uint32_t i = 0; i < entries; ++i) {
    uint8_t name_size = 0;
    uint32_t value_size = 0;
    if (!in.U8(name_size) || !in.Skip(name_size) || !in.Varint(value_size) || !in.Skip(value_size)) {
      return Corrupt("metadata entry");
    }
  }
  uint32_t children = 0;
  if (!in.Varint(children)) return Corrupt("metadata block count");
  for (uint32_t i = 0; i < children; ++i) {
    uint8_t name_size = 0;
    if (!in.U8(name_size) || !in.Skip(name_size)) return Corrupt("metadata block name");
    LSQSURF_RETURN_IF_ERROR(SkipMetadata(in, depth + 1));
  }
  return absl::OkStatus();
}

// Per-attribute metadata (each keyed by an attribute id), then the geometry's own.
absl::Status SkipGeometryMetadata(ByteReader& in) {
  uint32_t attributes = 0;
  if (!in.Varint(attributes)) return Corrupt("attribute metadata count");
  for (uint32_t i = 0; i < attributes; ++i) {
    uint32_t unique_id = 0;
    if (!in.Varint(unique_id)) return Corrupt("attribute metadata id");
    LSQSURF_RETURN_IF_ERROR(SkipMetadata(in, 1));
  }
  return SkipMetadata(in, 0);
}

// Bytes of one component of Draco's DataType 1..11 (INT8 … BOOL); 0 for anything else.
uint64_t ComponentBytes(uint8_t data_type) {
  static constexpr uint8_t kBytes[] = {0, 1, 1, 2, 2, 4, 4, 8, 8, 4, 8, 1};
  return data_type < sizeof(kBytes) ? kBytes[data_type] : 0;
}

// The attribute descriptors of a point cloud, which follow its point count directly. Draco keeps
// each decoded value and an integer copy while it decodes, hence the 4 extra bytes a component.
absl::StatusOr<uint64_t> ReadAttributeBytesPerPoint(ByteReader& in) {
  uint8_t decoders = 0;
  if (!in.U8(decoders)) return Corrupt("attribute decoder count");
  uint64_t per_point = 0;
  for (uint8_t d = 0; d < decoders; ++d) {
    uint32_t attributes = 0;
    if (!in.Varint(attributes) || attributes == 0) return Corrupt("attribute count");
    if (attributes > in.remaining() / 5) return Corrupt("more attributes than the data can describe");
    for (uint32_t a = 0; a < attributes; ++a) {
      uint8_t type = 0, data_type = 0, components = 0, normalized = 0;
      uint32_t unique_id = 0;
      if (!in.U8(type) || !in.U8(data_type) || !in.U8(components) || !in.U8(normalized) || !in.Varint(unique_id)) {
        return Corrupt("attribute descriptor");
      }
      const uint64_t bytes = ComponentBytes(data_type);
      if (bytes == 0 || components == 0) return Corrupt("attribute type");
      per_point += components * (bytes + 4);
    }
  }
  return per_point;
}

}  // namespace

absl::StatusOr<DracoClaim> ReadDracoClaim(std::string_view bytes) {
  ByteReader in(bytes);
  if (bytes.substr(0, 5) != "DRACO" || !in.Skip(5)) {
    return absl::InvalidArgumentError("the data is not Draco (it does not start with \"DRACO\")");
  }
  uint8_t major = 0, minor = 0, type = 0, method = 0;
  uint16_t flags = 0;
  if (!in.U8(major) || !in.U8(minor) || !in.U8(type) || !in.U8(method) || !in.U16(flags)) {
    return Corrupt("header");
  }
  if (major != 2 || minor < 2) {
    return absl::InvalidArgumentError(
        core::StrCat("Draco bitstream version ", int{major}, ".", int{minor},
                     " is not accepted; re-encode the data with Draco 1.3 or newer (bitstream 2.2 or later)"));
  }
  if ((flags & kMetadataFlag) != 0) LSQSURF_RETURN_IF_ERROR(SkipGeometryMetadata(in));
  DracoClaim claim;
  if (type == kPointCloud && method <= kKdTreeMethod) {
    // Before 2.3 the kd-tree coder keeps a second point count of its own deep in the stream, and
    // Draco allocates that one unchecked.
    if (method == kKdTreeMethod && minor < 3) {
      return absl::InvalidArgumentError(
          "kd-tree coded Draco point clouds of bitstream 2.2 are not accepted; re-encode the data with a current "
          "Draco");
    }
    int32_t points = 0;
    if (!in.I32(points) || points < 0) return Corrupt("point count");
    claim.points = static_cast<uint64_t>(points);
    claim.reorders_points = method == kKdTreeMethod;
    auto per_point = ReadAttributeBytesPerPoint(in);
    if (!per_point.ok()) return per_point.status();
    claim.attribute_bytes_per_point = *per_point;
    return claim;
  }
  if (type == kTriangleMesh && method <= kEdgebreakerMethod) {
    claim.is_mesh = true;
    uint8_t traversal = 0;
    if (method == kEdgebreakerMethod && !in.U8(traversal)) return Corrupt("Edgebreaker traversal");
    uint32_t first = 0, second = 0;
    if (!in.Varint(first) || !in.Varint(second)) return Corrupt("vertex and face counts");
    // Sequential meshes give faces then points; Edgebreaker gives vertices then faces.
    claim.faces = method == kEdgebreakerMethod ? second : first;
    claim.points = method == kEdgebreakerMethod ? first : second;
    if (claim.faces > 0xffffffffu / 3) return Corrupt("face count");
    return claim;
  }
  return absl::InvalidArgumentError(
      core::StrCat("the Draco data has geometry type ", int{type}, " and method ", int{method},
                   "; only point clouds (sequential or kd-tree) and triangle meshes are read"));
}

}  // namespace lsqsurf::io
