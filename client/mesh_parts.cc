#include <cstdio>
#include <filesystem>
#include <fstream>
#include <vector>

#include "client/client.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"
#include "worker/io/mesh_part.h"

namespace lsqsurf::client {
namespace {

// The body of a PLY or OBJ written as the parts come: vertices to one file, faces to another,
// joined under a header once the counts are known.
class PartWriter {
 public:
  PartWriter(std::string path, io::FileFormat format)
      : path_(std::move(path)),
        format_(format),
        vertex_path_(path_ + ".vertices.tmp"),
        face_path_(path_ + ".faces.tmp"),
        vertices_(vertex_path_, std::ios::binary | std::ios::trunc),
        faces_(face_path_, std::ios::binary | std::ios::trunc) {}
  ~PartWriter() {
    std::error_code ignored;
    std::filesystem::remove(vertex_path_, ignored);
    std::filesystem::remove(face_path_, ignored);
  }

  absl::Status Add(const io::MeshPart& part) {
    if (part.first_vertex != vertex_count_) {
      return absl::DataLossError(core::StrCat("mesh part numbering breaks at vertex ", vertex_count_));
    }
    if (vertex_count_ == 0) {
      with_normals_ = !part.normals.empty();
      for (const core::ScalarAttribute& a : part.attributes) attributes_.push_back(a.name);
    }
    if (with_normals_ != !part.normals.empty() || attributes_.size() != part.attributes.size()) {
      return absl::DataLossError("mesh parts disagree on their normals or attributes");
    }
    vertex_count_ += static_cast<int64_t>(part.vertices.size());
    if (vertex_count_ > INT32_MAX) return absl::ResourceExhaustedError("more than 2^31 vertices; write .drc parts");
    face_count_ += static_cast<int64_t>(part.faces.size());
    if (format_ == io::FileFormat::kPly) {
      AddPly(part);
    } else {
      AddObj(part);
    }
    return vertices_ && faces_ ? absl::OkStatus()
                               : absl::ResourceExhaustedError(core::StrCat(path_, ": cannot write (disk full?)"));
  }

  absl::Status Finish() {
    vertices_.close();
    faces_.close();
    const std::string tmp = path_ + ".tmp";
    {
      std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
      out << Header();
      for (const std::string* piece : {&vertex_path_, &face_path_}) {
        std::ifstream in(*piece, std::ios::binary);
        out << in.rdbuf();
      }
      out.close();
      if (!out) return absl::ResourceExhaustedError(core::StrCat(path_, ": cannot write (disk full?)"));
    }
    std::error_code error;
    std::filesystem::rename(tmp, path_, error);
    if (error) return absl::PermissionDeniedError(core::StrCat(path_, ": ", error.message()));
    return absl::OkStatus();
  }

 private:
  void AddPly(const io::MeshPart& part) {
    std::vector<float> row;
    for (size_t v = 0; v < part.vertices.size(); ++v) {
      row.assign(part.vertices[v].data(), part.vertices[v].data() + 3);
      if (with_normals_) row.insert(row.end(), part.normals[v].data(), part.normals[v].data() + 3);
      for (const core::ScalarAttribute& a : part.attributes) row.push_back(a.values[v]);
      vertices_.write(reinterpret_cast<const char*>(row.data()), static_cast<std::streamsize>(row.size() * 4));
    }
    for (const auto& f : part.faces) {
      const char count = 3;
      const int32_t corners[3] = {static_cast<int32_t>(f[0]), static_cast<int32_t>(f[1]), static_cast<int32_t>(f[2])};
      faces_.write(&count, 1);
      faces_.write(reinterpret_cast<const char*>(corners), sizeof(corners));
    }
  }

  void AddObj(const io::MeshPart& part) {
    char line[160];
    for (size_t v = 0; v < part.vertices.size(); ++v) {
      const auto& p = part.vertices[v];
      vertices_.write(line, std::snprintf(line, sizeof(line), "v %.9g %.9g %.9g\n", p.x(), p.y(), p.z()));
      if (!with_normals_) continue;
      const auto& n = part.normals[v];
      vertices_.write(line, std::snprintf(line, sizeof(line), "vn %.9g %.9g %.9g\n", n.x(), n.y(), n.z()));
    }
    for (const auto& f : part.faces) {
      const long long a = f[0] + 1, b = f[1] + 1, c = f[2] + 1;
      const int n = with_normals_
                        ? std::snprintf(line, sizeof(line), "f %lld//%lld %lld//%lld %lld//%lld\n", a, a, b, b, c, c)
                        : std::snprintf(line, sizeof(line), "f %lld %lld %lld\n", a, b, c);
      faces_.write(line, n);
    }
  }

  std::string Header() const {
    if (format_ == io::FileFormat::kObj) return "# lsqsurf mesh, written part by part\n";
    std::string header = core::StrCat("ply\nformat binary_little_endian 1.0\nelement vertex ", vertex_count_,
                                      "\nproperty float x\nproperty float y\nproperty float z\n");
    if (with_normals_) header += "property float nx\nproperty float ny\nproperty float nz\n";
    for (const std::string& name : attributes_) core::StrAppend(&header, "property float ", name, "\n");
    core::StrAppend(&header, "element face ", face_count_, "\nproperty list uchar int vertex_indices\nend_header\n");
    return header;
  }

  std::string path_;
  io::FileFormat format_;
  std::string vertex_path_, face_path_;
  std::ofstream vertices_, faces_;
  bool with_normals_ = false;
  std::vector<std::string> attributes_;  // Per-vertex scalars (PLY only; OBJ has no place for them).
  int64_t vertex_count_ = 0, face_count_ = 0;
};

}  // namespace

std::vector<std::string> MeshParts(const v1::Job& job) {
  std::vector<std::string> parts;
  for (const std::string& name : job.results()) {
    if (name.starts_with("mesh-part-") && name.ends_with(".lqm")) parts.push_back(name);
  }
  return parts;
}

absl::Status WriteMeshParts(size_t parts, const std::function<absl::StatusOr<std::string>(size_t part)>& fetch,
                            const std::string& path) {
  auto format = io::FormatFromPath(path);
  if (!format.ok()) return format.status();
  if (*format == io::FileFormat::kPly || *format == io::FileFormat::kObj) {
    PartWriter writer(path, *format);
    for (size_t i = 0; i < parts; ++i) {
      auto bytes = fetch(i);
      if (!bytes.ok()) return bytes.status();
      auto part = io::DecodeMeshPart(*bytes);
      if (!part.ok()) return part.status();
      LSQSURF_RETURN_IF_ERROR(writer.Add(*part));
    }
    return writer.Finish();
  }
  // Other formats take the mesh whole.
  core::TriangleMesh mesh;
  for (size_t i = 0; i < parts; ++i) {
    auto bytes = fetch(i);
    if (!bytes.ok()) return bytes.status();
    auto part = io::DecodeMeshPart(*bytes);
    if (!part.ok()) return part.status();
    if (part->first_vertex != static_cast<int64_t>(mesh.vertices.size())) {
      return absl::DataLossError("mesh part numbering breaks");
    }
    mesh.vertices.insert(mesh.vertices.end(), part->vertices.begin(), part->vertices.end());
    mesh.normals.insert(mesh.normals.end(), part->normals.begin(), part->normals.end());
    for (const auto& f : part->faces) {
      mesh.faces.push_back({static_cast<uint32_t>(f[0]), static_cast<uint32_t>(f[1]), static_cast<uint32_t>(f[2])});
    }
  }
  if (mesh.normals.size() != mesh.vertices.size()) mesh.normals.clear();
  return io::WriteMeshFile(path, mesh);
}

absl::StatusOr<std::vector<std::string>> WriteMeshPartFiles(
    size_t parts, const std::function<absl::StatusOr<std::string>(size_t part)>& fetch, const std::string& directory) {
  std::error_code error;
  std::filesystem::create_directories(directory, error);
  if (error) return absl::PermissionDeniedError(core::StrCat(directory, ": ", error.message()));
  io::SelfContainedParts joiner;
  std::vector<std::string> written;
  for (size_t i = 0; i < parts; ++i) {
    auto bytes = fetch(i);
    if (!bytes.ok()) return bytes.status();
    auto part = io::DecodeMeshPart(*bytes);
    if (!part.ok()) return part.status();
    auto piece = joiner.Next(*part);
    if (!piece.ok()) return piece.status();
    char name[48];
    std::snprintf(name, sizeof(name), "mesh-part-%05zu.drc", i);
    const std::string path = (std::filesystem::path(directory) / name).string();
    // Positions kept exact (not quantized over each tile's own box), so that the vertices two
    // tiles share stay equal and the tiles weld by position.
    io::WriteOptions options;
    options.draco.position_bits = 0;
    LSQSURF_RETURN_IF_ERROR(io::WriteMeshFile(path, *piece, options));
    written.push_back(path);
  }
  return written;
}

}  // namespace lsqsurf::client
