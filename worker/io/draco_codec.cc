#include "worker/io/draco_codec.h"

#include <draco/compression/decode.h>
#include <draco/compression/encode.h>
#include <draco/mesh/mesh.h>
#include <draco/metadata/geometry_metadata.h>
#include <draco/point_cloud/point_cloud.h>
#include <tbb/parallel_sort.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/draco_header.h"

namespace lsqsurf::io {
namespace {

constexpr char kNameEntry[] = "name";

int AddFloatAttribute(draco::PointCloud& pc, draco::GeometryAttribute::Type type, int components, const float* data,
                      size_t count) {
  draco::GeometryAttribute ga;
  ga.Init(type, nullptr, static_cast<uint8_t>(components), draco::DT_FLOAT32, false,
          sizeof(float) * static_cast<size_t>(components), 0);
  const int id = pc.AddAttribute(ga, /*identity_mapping=*/true, static_cast<uint32_t>(count));
  draco::PointAttribute* att = pc.attribute(id);
  for (size_t i = 0; i < count; ++i) {
    att->SetAttributeValue(draco::AttributeValueIndex(static_cast<uint32_t>(i)),
                           data + i * static_cast<size_t>(components));
  }
  return id;
}

// Adds positions, normals and named scalars; `normals`/`attributes` may be empty.
void FillPointCloud(draco::PointCloud& pc, const std::vector<core::Vec3f>& positions,
                    const std::vector<core::Vec3f>& normals, const std::vector<core::ScalarAttribute>& attributes) {
  const size_t n = positions.size();
  pc.set_num_points(static_cast<uint32_t>(n));
  AddFloatAttribute(pc, draco::GeometryAttribute::POSITION, 3, positions.front().data(), n);
  if (normals.size() == n) AddFloatAttribute(pc, draco::GeometryAttribute::NORMAL, 3, normals.front().data(), n);
  for (const auto& a : attributes) {
    if (a.values.size() != n) continue;
    const int id = AddFloatAttribute(pc, draco::GeometryAttribute::GENERIC, 1, a.values.data(), n);
    auto md = std::make_unique<draco::AttributeMetadata>();
    md->AddEntryString(kNameEntry, a.name);
    pc.AddAttributeMetadata(id, std::move(md));
  }
}

draco::Encoder MakeEncoder(const DracoOptions& o) {
  draco::Encoder enc;
  if (o.position_bits > 0) enc.SetAttributeQuantization(draco::GeometryAttribute::POSITION, o.position_bits);
  enc.SetAttributeQuantization(draco::GeometryAttribute::NORMAL, o.normal_bits);
  enc.SetAttributeQuantization(draco::GeometryAttribute::GENERIC, o.attribute_bits);
  enc.SetSpeedOptions(o.speed, o.speed);
  return enc;
}

// Draco reads a BOOL attribute's bytes as C++ bools, which is undefined for any byte but 0 and 1.
bool IsNumeric(const draco::PointAttribute& attribute) {
  return attribute.data_type() != draco::DT_BOOL && attribute.data_type() != draco::DT_INVALID;
}

absl::Status DracoError(std::string_view what, const draco::Status& s) {
  return absl::InvalidArgumentError(
      core::StrCat(what, ": ", s.error_msg_string(), " (is the data truncated or corrupt?)"));
}

// Reads positions, normals and named scalars of the points (vertices) of a decoded geometry.
absl::Status ExtractPoints(const draco::PointCloud& pc, std::vector<core::Vec3f>& positions,
                           std::vector<core::Vec3f>& normals, std::vector<core::ScalarAttribute>& attributes) {
  const draco::PointAttribute* pos = pc.GetNamedAttribute(draco::GeometryAttribute::POSITION);
  if (pos == nullptr) return absl::InvalidArgumentError("Draco data has no position attribute");
  if (pos->num_components() != 3 || !IsNumeric(*pos)) {
    return absl::InvalidArgumentError(core::StrCat("Draco positions have ", pos->num_components(),
                                                   " components of type ", int{pos->data_type()},
                                                   "; 3 numbers are required"));
  }
  const uint32_t n = pc.num_points();
  positions.resize(n);
  for (uint32_t i = 0; i < n; ++i) {
    pos->ConvertValue<float>(pos->mapped_index(draco::PointIndex(i)), 3, positions[i].data());
  }
  const draco::PointAttribute* nrm = pc.GetNamedAttribute(draco::GeometryAttribute::NORMAL);
  if (nrm != nullptr) {
    if (nrm->num_components() != 3 || !IsNumeric(*nrm)) {
      return absl::InvalidArgumentError(core::StrCat("Draco normals have ", nrm->num_components(),
                                                     " components of type ", int{nrm->data_type()},
                                                     "; 3 numbers are required"));
    }
    normals.resize(n);
    for (uint32_t i = 0; i < n; ++i) {
      nrm->ConvertValue<float>(nrm->mapped_index(draco::PointIndex(i)), 3, normals[i].data());
    }
  }
  const int generic_count = pc.NumNamedAttributes(draco::GeometryAttribute::GENERIC);
  for (int g = 0; g < generic_count; ++g) {
    const draco::PointAttribute* att = pc.GetNamedAttribute(draco::GeometryAttribute::GENERIC, g);
    if (att->num_components() != 1 || !IsNumeric(*att)) continue;  // Only scalars are product data.
    core::ScalarAttribute out;
    out.name = core::StrCat("generic_", g);
    if (const draco::AttributeMetadata* md =
            pc.GetAttributeMetadataByAttributeId(pc.GetAttributeIdByUniqueId(att->unique_id()))) {
      md->GetEntryString(kNameEntry, &out.name);
    }
    out.values.resize(n);
    for (uint32_t i = 0; i < n; ++i) {
      att->ConvertValue<float>(att->mapped_index(draco::PointIndex(i)), 1, &out.values[i]);
    }
    attributes.push_back(std::move(out));
  }
  return absl::OkStatus();
}

// Refuses a stream whose header claims more than `limits` allow, before Draco allocates it.
absl::Status CheckClaim(std::string_view bytes, const DracoDecodeLimits& limits) {
  auto claim = ReadDracoClaim(bytes);
  if (!claim.ok()) return claim.status();
  if (claim->points > static_cast<uint64_t>(limits.max_points)) {
    return absl::ResourceExhaustedError(
        core::StrCat("the cloud has ", claim->points, " points; this server accepts at most ", limits.max_points));
  }
  // Positions as floats and Draco's integer copy; a mesh's corner table and faces besides.
  const uint64_t per_point = std::max<uint64_t>(claim->attribute_bytes_per_point, 24);
  const double needed =
      static_cast<double>(claim->points) * static_cast<double>(per_point) + static_cast<double>(claim->faces) * 36.0;
  const double allowed = static_cast<double>(limits.max_expansion) * static_cast<double>(bytes.size()) +
                         static_cast<double>(limits.expansion_allowance_bytes);
  if (needed > allowed) {
    return absl::InvalidArgumentError(core::StrCat("the Draco header claims ", claim->points, " points",
                                                   claim->is_mesh ? core::StrCat(" and ", claim->faces, " faces") : "",
                                                   " in only ", bytes.size(),
                                                   " bytes; no real data compresses that far, so it is corrupt"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status Validate(const DracoOptions& o) {
  if (o.position_bits < 0 || o.position_bits > 30) {
    return absl::InvalidArgumentError("Draco position bits must be 0 (lossless) or 1..30");
  }
  for (int bits : {o.normal_bits, o.attribute_bits}) {
    if (bits < 1 || bits > 30) return absl::InvalidArgumentError("Draco quantization bits must be 1..30");
  }
  if (o.speed < 0 || o.speed > 10) return absl::InvalidArgumentError("Draco speed must be 0..10");
  return absl::OkStatus();
}

absl::StatusOr<std::string> EncodeDracoPointCloud(const core::PointCloud& cloud, const DracoOptions& options) {
  if (absl::Status s = Validate(options); !s.ok()) return s;
  if (cloud.empty()) return absl::InvalidArgumentError("cannot encode an empty point cloud");
  if (const int64_t bad = core::FindNonFinite(cloud.positions); bad >= 0 && options.position_bits > 0) {
    return absl::InvalidArgumentError(core::StrCat("point ", bad, " has a NaN or infinite coordinate"));
  }
  draco::PointCloud pc;
  FillPointCloud(pc, cloud.positions, cloud.normals, cloud.attributes);
  draco::Encoder enc = MakeEncoder(options);
  draco::EncoderBuffer buffer;
  const draco::Status s = enc.EncodePointCloudToBuffer(pc, &buffer);
  if (!s.ok()) return absl::InternalError(core::StrCat("Draco encoding failed: ", s.error_msg_string()));
  return std::string(buffer.data(), buffer.size());
}

absl::StatusOr<std::string> EncodeDracoMesh(const core::TriangleMesh& mesh, const DracoOptions& options) {
  if (absl::Status s = Validate(options); !s.ok()) return s;
  if (mesh.vertices.empty() || mesh.faces.empty()) {
    return absl::InvalidArgumentError("cannot encode a mesh without faces");
  }
  draco::Mesh dm;
  FillPointCloud(dm, mesh.vertices, mesh.normals, mesh.vertex_attributes);
  dm.SetNumFaces(mesh.faces.size());
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    const auto& t = mesh.faces[f];
    dm.SetFace(draco::FaceIndex(static_cast<uint32_t>(f)),
               {draco::PointIndex(t[0]), draco::PointIndex(t[1]), draco::PointIndex(t[2])});
  }
  draco::Encoder enc = MakeEncoder(options);
  draco::EncoderBuffer buffer;
  const draco::Status s = enc.EncodeMeshToBuffer(dm, &buffer);
  if (!s.ok()) return absl::InternalError(core::StrCat("Draco encoding failed: ", s.error_msg_string()));
  return std::string(buffer.data(), buffer.size());
}

absl::StatusOr<DracoGeometry> PeekDracoGeometry(std::string_view bytes) {
  if (bytes.empty()) return absl::InvalidArgumentError("the Draco data is empty");
  draco::DecoderBuffer buffer;
  buffer.Init(bytes.data(), bytes.size());
  auto type = draco::Decoder::GetEncodedGeometryType(&buffer);
  if (!type.ok()) return DracoError("cannot read the Draco header", type.status());
  switch (type.value()) {
    case draco::POINT_CLOUD: return DracoGeometry::kPointCloud;
    case draco::TRIANGULAR_MESH: return DracoGeometry::kTriangleMesh;
    default: return absl::InvalidArgumentError("the Draco data holds neither a point cloud nor a triangle mesh");
  }
}

absl::StatusOr<core::PointCloud> DecodeDracoPointCloud(std::string_view bytes, const DracoDecodeLimits& limits) {
  if (bytes.empty()) return absl::InvalidArgumentError("the Draco data is empty");
  LSQSURF_RETURN_IF_ERROR(CheckClaim(bytes, limits));
  draco::DecoderBuffer buffer;
  buffer.Init(bytes.data(), bytes.size());
  draco::Decoder decoder;
  auto decoded = decoder.DecodePointCloudFromBuffer(&buffer);
  if (!decoded.ok()) return DracoError("cannot decode the Draco point cloud", decoded.status());
  std::unique_ptr<draco::PointCloud> pc = std::move(decoded).value();
  core::PointCloud cloud;
  if (absl::Status s = ExtractPoints(*pc, cloud.positions, cloud.normals, cloud.attributes); !s.ok()) return s;
  return cloud;
}

absl::StatusOr<core::TriangleMesh> DecodeDracoMesh(std::string_view bytes, const DracoDecodeLimits& limits) {
  if (bytes.empty()) return absl::InvalidArgumentError("the Draco data is empty");
  auto type = PeekDracoGeometry(bytes);
  if (!type.ok()) return type.status();
  if (*type != DracoGeometry::kTriangleMesh) {
    return absl::InvalidArgumentError("the Draco data holds a point cloud, not a triangle mesh");
  }
  LSQSURF_RETURN_IF_ERROR(CheckClaim(bytes, limits));
  draco::DecoderBuffer buffer;
  buffer.Init(bytes.data(), bytes.size());
  draco::Decoder decoder;
  auto decoded = decoder.DecodeMeshFromBuffer(&buffer);
  if (!decoded.ok()) return DracoError("cannot decode the Draco mesh", decoded.status());
  std::unique_ptr<draco::Mesh> dm = std::move(decoded).value();
  core::TriangleMesh mesh;
  if (absl::Status s = ExtractPoints(*dm, mesh.vertices, mesh.normals, mesh.vertex_attributes); !s.ok()) return s;
  mesh.faces.resize(dm->num_faces());
  for (uint32_t f = 0; f < dm->num_faces(); ++f) {
    const auto& face = dm->face(draco::FaceIndex(f));
    for (int k = 0; k < 3; ++k) {
      const uint32_t v = face[static_cast<size_t>(k)].value();
      if (v >= mesh.vertices.size()) return absl::InvalidArgumentError("Draco mesh face refers to a missing vertex");
      mesh.faces[f][static_cast<size_t>(k)] = v;
    }
  }
  return mesh;
}

// Distinct positions after Draco's quantization round trip, simulated in its float arithmetic: q = floor((x -
// min) * (2^bits - 1) / range + 0.5) with `range` the box's largest extent, then x' = q * (range / (2^bits - 1))
// + min. Past ~23 bits the step falls below a float's resolution at the coordinates, so distinct integers can
// decode to the same float: the round trip, not the integers, decides what a client sees.
int64_t DistinctAfterQuantization(const std::vector<core::Vec3f>& vertices, int bits) {
  Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
  Eigen::Vector3f hi = -lo;
  for (const auto& v : vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
  float range = (hi - lo).maxCoeff();
  if (!(range > 0)) range = 1;
  const auto max_quantized = static_cast<float>((uint32_t{1} << bits) - 1);
  const float inverse_delta = max_quantized / range, delta = range / max_quantized;
  // Bit patterns of the decoded floats: equal patterns are equal positions (x' is never -0).
  std::vector<std::array<uint32_t, 3>> delivered(vertices.size());
  for (size_t i = 0; i < vertices.size(); ++i) {
    for (int c = 0; c < 3; ++c) {
      const auto q = static_cast<int32_t>(std::floor((vertices[i][c] - lo[c]) * inverse_delta + 0.5f));
      delivered[i][static_cast<size_t>(c)] = std::bit_cast<uint32_t>(static_cast<float>(q) * delta + lo[c]);
    }
  }
  tbb::parallel_sort(delivered.begin(), delivered.end());
  return std::unique(delivered.begin(), delivered.end()) - delivered.begin();
}

// The fewest bits from 16 to 30 at which quantization keeps every distinct position apart
// (30 when none does), by bisection on the simulated quantization.
int FewestPositionBits(const core::TriangleMesh& mesh, int64_t distinct) {
  int lo = 16, hi = 30;
  if (DistinctAfterQuantization(mesh.vertices, lo) >= distinct) return lo;
  while (hi - lo > 1) {
    const int mid = (lo + hi) / 2;
    (DistinctAfterQuantization(mesh.vertices, mid) >= distinct ? hi : lo) = mid;
  }
  return hi;
}

}  // namespace lsqsurf::io
