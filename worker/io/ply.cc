#include "worker/io/ply.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <optional>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/point_stream.h"
#include "worker/io/text_scan.h"

namespace lsqsurf::io {
namespace {

using internal::LineReader;
using internal::NextToken;
using internal::ParseNumber;

enum class Type { kInt8, kUint8, kInt16, kUint16, kInt32, kUint32, kFloat32, kFloat64 };

std::optional<Type> ParseType(std::string_view s) {
  if (s == "char" || s == "int8") return Type::kInt8;
  if (s == "uchar" || s == "uint8") return Type::kUint8;
  if (s == "short" || s == "int16") return Type::kInt16;
  if (s == "ushort" || s == "uint16") return Type::kUint16;
  if (s == "int" || s == "int32") return Type::kInt32;
  if (s == "uint" || s == "uint32") return Type::kUint32;
  if (s == "float" || s == "float32") return Type::kFloat32;
  if (s == "double" || s == "float64") return Type::kFloat64;
  return std::nullopt;
}

size_t TypeSize(Type t) {
  switch (t) {
    case Type::kInt8:
    case Type::kUint8: return 1;
    case Type::kInt16:
    case Type::kUint16: return 2;
    case Type::kInt32:
    case Type::kUint32:
    case Type::kFloat32: return 4;
    case Type::kFloat64: return 8;
  }
  return 0;
}

struct Property {
  std::string name;
  Type type = Type::kFloat32;
  bool is_list = false;
  Type count_type = Type::kUint8;
};

struct Element {
  std::string name;
  uint64_t count = 0;
  std::vector<Property> properties;
};

// Reads values from a binary or ascii body with bounds checks; every failure names where.
// A value of type T from its bytes in native order (memcpy: `raw` need not be aligned).
template <class T>
double Load(const unsigned char* raw) {
  T v;
  std::memcpy(&v, raw, sizeof(T));
  return static_cast<double>(v);
}

class BodyReader {
 public:
  BodyReader(std::string_view body, PlyFormat format, size_t body_offset, size_t first_line)
      : body_(body), format_(format), body_offset_(body_offset), lines_(body), first_line_(first_line) {}

  // Starts the next element instance (ascii: the next non-empty line).
  bool BeginRecord() {
    if (format_ != PlyFormat::kAscii) return true;
    while (lines_.Next(line_)) {
      if (line_.find_first_not_of(" \t") != std::string_view::npos) return true;
    }
    return false;
  }
  bool EndRecord() const {  // Ascii: nothing may be left on the line.
    if (format_ != PlyFormat::kAscii) return true;
    std::string_view rest = line_;
    return NextToken(rest).empty();
  }
  bool Read(Type t, double& out) {
    if (format_ == PlyFormat::kAscii) {
      const std::string_view tok = NextToken(line_);
      if (t == Type::kFloat32 || t == Type::kFloat64) return ParseNumber(tok, out);
      int64_t v = 0;
      if (!ParseNumber(tok, v)) return false;
      out = static_cast<double>(v);
      return true;
    }
    const size_t n = TypeSize(t);
    if (pos_ + n > body_.size()) return false;
    unsigned char raw[8];
    std::memcpy(raw, body_.data() + pos_, n);
    pos_ += n;
    const bool little = format_ == PlyFormat::kBinaryLittleEndian;
    if (little != (std::endian::native == std::endian::little)) std::reverse(raw, raw + n);
    switch (t) {
      case Type::kInt8: out = Load<int8_t>(raw); break;
      case Type::kUint8: out = Load<uint8_t>(raw); break;
      case Type::kInt16: out = Load<int16_t>(raw); break;
      case Type::kUint16: out = Load<uint16_t>(raw); break;
      case Type::kInt32: out = Load<int32_t>(raw); break;
      case Type::kUint32: out = Load<uint32_t>(raw); break;
      case Type::kFloat32: out = Load<float>(raw); break;
      case Type::kFloat64: out = Load<double>(raw); break;
    }
    return true;
  }
  std::string Where() const {
    if (format_ == PlyFormat::kAscii) {
      return core::StrCat("line ", first_line_ + lines_.line_number());
    }
    return core::StrCat("byte ", body_offset_ + pos_);
  }
  size_t remaining() const { return body_.size() - pos_; }
  size_t consumed() const { return format_ == PlyFormat::kAscii ? lines_.offset() : pos_; }  // Bytes of the body.
  PlyFormat format() const { return format_; }

 private:
  std::string_view body_;
  PlyFormat format_;
  size_t body_offset_;
  size_t pos_ = 0;
  LineReader lines_;
  std::string_view line_;
  size_t first_line_;
};

absl::Status HeaderError(std::string_view name, size_t line, std::string_view what) {
  return absl::InvalidArgumentError(core::StrCat(name, ": PLY header line ", line, ": ", what));
}

}  // namespace

namespace {

struct PlyHeader {
  PlyFormat format = PlyFormat::kAscii;
  std::vector<Element> elements;
  size_t body_offset = 0;  // Bytes before the body.
  size_t lines = 0;        // Header lines (ASCII bodies count on from there).
};

// `property TYPE NAME` or `property list COUNT_TYPE ITEM_TYPE NAME`, after the keyword.
absl::StatusOr<Property> ParseProperty(std::string_view rest, std::string_view name, size_t ln) {
  Property p;
  const std::string_view t = NextToken(rest);
  if (t == "list") {
    p.is_list = true;
    const auto ct = ParseType(NextToken(rest));
    const auto it = ParseType(NextToken(rest));
    if (!ct || !it) return HeaderError(name, ln, "bad list property types");
    if (*ct == Type::kFloat32 || *ct == Type::kFloat64) {
      return HeaderError(name, ln, "list count type must be an integer type");
    }
    p.count_type = *ct;
    p.type = *it;
  } else {
    const auto pt = ParseType(t);
    if (!pt) return HeaderError(name, ln, core::StrCat("unknown property type '", t, "'"));
    p.type = *pt;
  }
  p.name = std::string(NextToken(rest));
  if (p.name.empty()) return HeaderError(name, ln, "property without a name");
  return p;
}

absl::StatusOr<PlyHeader> ParseHeader(std::string_view bytes, std::string_view name) {
  LineReader header(bytes);
  std::string_view line;
  if (!header.Next(line) || line != "ply") {
    return absl::InvalidArgumentError(core::StrCat(name, ": not a PLY file (no 'ply' magic)"));
  }
  PlyHeader out;
  bool has_format = false, ended = false;
  while (!ended && header.Next(line)) {
    std::string_view rest = line;
    const std::string_view key = NextToken(rest);
    const size_t ln = header.line_number();
    if (key.empty() || key == "comment" || key == "obj_info") continue;
    if (key == "format") {
      const std::string_view f = NextToken(rest), version = NextToken(rest);
      if (f == "ascii")
        out.format = PlyFormat::kAscii;
      else if (f == "binary_little_endian")
        out.format = PlyFormat::kBinaryLittleEndian;
      else if (f == "binary_big_endian")
        out.format = PlyFormat::kBinaryBigEndian;
      else
        return HeaderError(name, ln, core::StrCat("unknown format '", f, "'"));
      if (version != "1.0") return HeaderError(name, ln, core::StrCat("unsupported version '", version, "'"));
      has_format = true;
    } else if (key == "element") {
      Element e;
      e.name = std::string(NextToken(rest));
      if (e.name.empty() || !ParseNumber(NextToken(rest), e.count)) {
        return HeaderError(name, ln, "expected 'element NAME COUNT'");
      }
      out.elements.push_back(std::move(e));
    } else if (key == "property") {
      if (out.elements.empty()) return HeaderError(name, ln, "property before any element");
      auto p = ParseProperty(rest, name, ln);
      if (!p.ok()) return p.status();
      out.elements.back().properties.push_back(*std::move(p));
    } else if (key == "end_header") {
      ended = true;
    } else {
      return HeaderError(name, ln, core::StrCat("unknown keyword '", key, "'"));
    }
  }
  if (!ended) return absl::InvalidArgumentError(core::StrCat(name, ": PLY header has no end_header"));
  if (!has_format) return absl::InvalidArgumentError(core::StrCat(name, ": PLY header has no format line"));
  out.body_offset = header.offset();
  out.lines = header.line_number();
  return out;
}

// Where an element's properties land in the mesh.
struct ElementLayout {
  bool is_vertex = false, is_face = false;
  int x = -1, y = -1, z = -1, nx = -1, ny = -1, nz = -1, face_list = -1;
  std::vector<int> extra;  // Property index of each extra scalar attribute (vertices).

  explicit ElementLayout(const Element& e) : is_vertex(e.name == "vertex"), is_face(e.name == "face") {
    for (size_t i = 0; i < e.properties.size(); ++i) {
      const Property& p = e.properties[i];
      const int idx = static_cast<int>(i);
      if (is_vertex && !p.is_list) {
        int* slot = p.name == "x"    ? &x
                    : p.name == "y"  ? &y
                    : p.name == "z"  ? &z
                    : p.name == "nx" ? &nx
                    : p.name == "ny" ? &ny
                    : p.name == "nz" ? &nz
                                     : nullptr;
        if (slot != nullptr)
          *slot = idx;
        else
          extra.push_back(idx);
      }
      if (is_face && p.is_list && (p.name == "vertex_indices" || p.name == "vertex_index")) face_list = idx;
    }
  }
  bool has_normals() const { return nx >= 0 && ny >= 0 && nz >= 0; }
};

// Reads one element's records into `mesh`.
class ElementReader {
 public:
  ElementReader(std::string_view name, const Element& e, BodyReader& body, core::TriangleMesh& mesh)
      : name_(name), e_(e), layout_(e), body_(body), mesh_(mesh), scalars_(e.properties.size()) {}

  absl::Status Read(bool& saw_vertex) {
    LSQSURF_RETURN_IF_ERROR(CheckCount());
    if (MinRecordBytes() == 0) return absl::OkStatus();  // Nothing to read (CheckCount).
    if (layout_.is_vertex) {
      if (saw_vertex) return Fail("two vertex elements");
      saw_vertex = true;
      LSQSURF_RETURN_IF_ERROR(SizeVertices(e_.count));
    }
    if (layout_.is_face && layout_.face_list < 0) return Fail("PLY face element has no vertex_indices list");
    for (uint64_t r = 0; r < e_.count; ++r) LSQSURF_RETURN_IF_ERROR(ReadRecord(r));
    return absl::OkStatus();
  }

  // Streaming a vertex element: CheckCount() first, then records [first, first + n) into the
  // mesh's first n vertices, with their other properties.
  absl::Status ReadVertices(uint64_t first, uint64_t n) {
    LSQSURF_RETURN_IF_ERROR(SizeVertices(n));
    first_ = first;
    for (uint64_t r = first; r < first + n; ++r) LSQSURF_RETURN_IF_ERROR(ReadRecord(r));
    return absl::OkStatus();
  }

  // Every record takes at least one byte (binary) or two characters (ascii): a count larger
  // than that allows is a corrupt header, refused before any allocation.
  size_t MinRecordBytes() const {
    size_t min_record = 0;
    for (const Property& p : e_.properties) min_record += p.is_list ? TypeSize(p.count_type) : TypeSize(p.type);
    if (body_.format() == PlyFormat::kAscii) min_record = std::max<size_t>(1, 2 * e_.properties.size());
    return min_record;
  }

  absl::Status CheckCount() {
    const size_t min_record = MinRecordBytes();
    // Binary records without properties take no bytes: there is nothing to read, however many
    // the header declares (a loop over a count from the file would run for hours; fuzzing).
    if (min_record == 0)
      return layout_.is_vertex || layout_.is_face ? Fail("an element without properties") : absl::OkStatus();
    if (min_record > 0 && e_.count > body_.remaining() / min_record) {
      return Fail(core::StrCat("PLY element '", e_.name, "' declares ", e_.count,
                               " records but the file is too short for them (truncated?)"));
    }
    return absl::OkStatus();
  }

 private:
  absl::Status Fail(std::string_view what) const { return absl::InvalidArgumentError(core::StrCat(name_, ": ", what)); }
  absl::Status FailAt(const std::string& where, uint64_t r, std::string_view what) const {
    return Fail(core::StrCat(where, ": ", e_.name, " ", r, what));
  }
  float Scalar(int index) const { return static_cast<float>(scalars_[static_cast<size_t>(index)]); }

  absl::Status SizeVertices(uint64_t n) {
    if (layout_.x < 0 || layout_.y < 0 || layout_.z < 0) return Fail("PLY vertex element lacks x, y or z");
    mesh_.vertices.resize(n);
    if (layout_.has_normals()) mesh_.normals.resize(n);
    for (int k : layout_.extra) {
      mesh_.vertex_attributes.push_back({e_.properties[static_cast<size_t>(k)].name, std::vector<float>(n)});
    }
    return absl::OkStatus();
  }

  absl::Status ReadRecord(uint64_t r) {
    if (!body_.BeginRecord()) return Fail(core::StrCat("unexpected end of file in ", e_.name, " ", r));
    for (size_t i = 0; i < e_.properties.size(); ++i) {
      const Property& p = e_.properties[i];
      const std::string where = body_.Where();
      if (!p.is_list) {
        if (!body_.Read(p.type, scalars_[i])) {
          return FailAt(where, r, core::StrCat(": cannot read property '", p.name, "'"));
        }
        continue;
      }
      LSQSURF_RETURN_IF_ERROR(ReadList(p, static_cast<int>(i) == layout_.face_list, where, r));
    }
    if (!body_.EndRecord()) return FailAt(body_.Where(), r, " has more values than the header declares");
    if (layout_.is_vertex) {
      const uint64_t v = r - first_;
      mesh_.vertices[v] = core::Vec3f(Scalar(layout_.x), Scalar(layout_.y), Scalar(layout_.z));
      if (!mesh_.normals.empty())
        mesh_.normals[v] = core::Vec3f(Scalar(layout_.nx), Scalar(layout_.ny), Scalar(layout_.nz));
      for (size_t a = 0; a < layout_.extra.size(); ++a) mesh_.vertex_attributes[a].values[v] = Scalar(layout_.extra[a]);
    }
    return absl::OkStatus();
  }

  // A list property; the face list becomes a fan of triangles, other lists are skipped.
  absl::Status ReadList(const Property& p, bool is_face_list, const std::string& where, uint64_t r) {
    double count = 0;
    if (!body_.Read(p.count_type, count) || count < 0 || count > 1e6) {
      return FailAt(where, r, core::StrCat(": bad list length for '", p.name, "'"));
    }
    polygon_.clear();
    for (int j = 0; j < static_cast<int>(count); ++j) {
      double v = 0;
      if (!body_.Read(p.type, v)) return FailAt(body_.Where(), r, core::StrCat(": list '", p.name, "' is cut short"));
      if (!is_face_list) continue;
      if (v < 0 || v >= static_cast<double>(mesh_.vertices.size()) || v != std::floor(v)) {
        return Fail(core::StrCat(where, ": face ", r, " refers to vertex ", v, " but there are ", mesh_.vertices.size(),
                                 " vertices"));
      }
      polygon_.push_back(static_cast<uint32_t>(v));
    }
    if (!is_face_list) return absl::OkStatus();
    if (polygon_.size() < 3) return Fail(core::StrCat(where, ": face ", r, " has fewer than 3 vertices"));
    for (size_t j = 1; j + 1 < polygon_.size(); ++j) mesh_.faces.push_back({polygon_[0], polygon_[j], polygon_[j + 1]});
    return absl::OkStatus();
  }

  std::string_view name_;
  const Element& e_;
  ElementLayout layout_;
  BodyReader& body_;
  core::TriangleMesh& mesh_;
  std::vector<double> scalars_;
  std::vector<uint32_t> polygon_;
  uint64_t first_ = 0;  // The record that lands in vertex 0 (streaming).
};

// The vertex element, first in its file, a chunk at a time; the pages read are released.
class PlyVertexStream final : public PointStream {
 public:
  PlyVertexStream(std::shared_ptr<const MappedFile> file, PlyHeader header)
      : file_(std::move(file)),
        header_(std::move(header)),
        body_(file_->bytes().substr(std::min(header_.body_offset, file_->bytes().size())), header_.format,
              header_.body_offset, header_.lines),
        reader_(file_->path(), header_.elements[0], body_, chunk_) {}

  absl::Status Check() { return reader_.CheckCount(); }

  absl::StatusOr<core::PointCloud> Next(size_t max_points) override {
    const uint64_t n = std::min<uint64_t>(std::max<size_t>(max_points, 1), header_.elements[0].count - next_);
    LSQSURF_RETURN_IF_ERROR(reader_.ReadVertices(next_, n));
    next_ += n;
    file_->Release(header_.body_offset + body_.consumed());
    core::PointCloud cloud;
    cloud.positions = std::move(chunk_.vertices);
    cloud.normals = std::move(chunk_.normals);
    cloud.attributes = std::move(chunk_.vertex_attributes);
    chunk_ = {};
    return cloud;
  }

 private:
  std::shared_ptr<const MappedFile> file_;
  PlyHeader header_;
  BodyReader body_;
  core::TriangleMesh chunk_;
  ElementReader reader_;
  uint64_t next_ = 0;
};

}  // namespace

absl::StatusOr<std::unique_ptr<PointStream>> StreamPlyVertices(std::shared_ptr<const MappedFile> file) {
  auto header = ParseHeader(file->bytes(), file->path());
  if (!header.ok()) return header.status();
  if (header->elements.empty() || header->elements[0].name != "vertex") return nullptr;
  auto stream = std::make_unique<PlyVertexStream>(std::move(file), *std::move(header));
  LSQSURF_RETURN_IF_ERROR(stream->Check());
  return stream;
}

absl::StatusOr<core::TriangleMesh> ParsePly(std::string_view bytes, std::string_view name) {
  auto header = ParseHeader(bytes, name);
  if (!header.ok()) return header.status();
  const size_t offset = header->body_offset;
  BodyReader body(offset <= bytes.size() ? bytes.substr(offset) : std::string_view(), header->format, offset,
                  header->lines);
  core::TriangleMesh mesh;
  bool saw_vertex = false;
  for (const Element& e : header->elements) {
    LSQSURF_RETURN_IF_ERROR(ElementReader(name, e, body, mesh).Read(saw_vertex));
  }
  if (!saw_vertex) return absl::InvalidArgumentError(core::StrCat(name, ": PLY file has no vertex element"));
  return mesh;
}

namespace {

void Append(std::string& out, const void* p, size_t n, bool swap) {
  const auto* c = static_cast<const char*>(p);
  if (!swap) {
    out.append(c, n);
    return;
  }
  for (size_t i = 0; i < n; ++i) out.push_back(c[n - 1 - i]);
}

uint8_t ColourByte(float v) { return static_cast<uint8_t>(std::clamp(std::lround(v), 0L, 255L)); }

}  // namespace

std::string EncodePly(const core::TriangleMesh& mesh, PlyFormat format) {
  const bool normals = mesh.normals.size() == mesh.vertices.size() && !mesh.vertices.empty();
  std::string out = "ply\nformat ";
  out += format == PlyFormat::kAscii                ? "ascii"
         : format == PlyFormat::kBinaryLittleEndian ? "binary_little_endian"
                                                    : "binary_big_endian";
  out += " 1.0\ncomment written by lsqsurf\n";
  core::StrAppend(&out, "element vertex ", mesh.vertices.size(), "\n");
  out += "property float x\nproperty float y\nproperty float z\n";
  if (normals) out += "property float nx\nproperty float ny\nproperty float nz\n";
  // Colour as viewers read it: red, green and blue as uchar, when all three are there.
  const auto channels = core::ColourChannels(mesh.vertex_attributes, mesh.vertices.size());
  auto as_byte = [&](const core::ScalarAttribute& a) {
    return std::find(channels.begin(), channels.end(), &a) != channels.end();
  };
  for (const auto& a : mesh.vertex_attributes) {
    core::StrAppend(&out, "property ", as_byte(a) ? "uchar " : "float ", a.name, "\n");
  }
  if (!mesh.faces.empty()) {
    core::StrAppend(&out, "element face ", mesh.faces.size(), "\nproperty list uchar int vertex_indices\n");
  }
  out += "end_header\n";
  if (format == PlyFormat::kAscii) {
    for (size_t i = 0; i < mesh.vertices.size(); ++i) {
      const auto& v = mesh.vertices[i];
      std::vector<float> row = {v.x(), v.y(), v.z()};
      if (normals) row.insert(row.end(), {mesh.normals[i].x(), mesh.normals[i].y(), mesh.normals[i].z()});
      for (size_t k = 0; k < row.size(); ++k) {
        if (k > 0) out.push_back(' ');
        internal::AppendFloat(out, row[k]);
      }
      for (const auto& a : mesh.vertex_attributes) {
        out.push_back(' ');
        if (as_byte(a)) {
          core::StrAppend(&out, static_cast<int>(ColourByte(a.values[i])));
        } else {
          internal::AppendFloat(out, a.values[i]);
        }
      }
      out.push_back('\n');
    }
    for (const auto& f : mesh.faces) core::StrAppend(&out, "3 ", f[0], " ", f[1], " ", f[2], "\n");
    return out;
  }
  const bool swap = (format == PlyFormat::kBinaryLittleEndian) != (std::endian::native == std::endian::little);
  out.reserve(out.size() + mesh.vertices.size() * 4 * (3 + 3 * normals + mesh.vertex_attributes.size()) +
              mesh.faces.size() * 13);
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    for (int k = 0; k < 3; ++k) Append(out, &mesh.vertices[i][k], 4, swap);
    if (normals)
      for (int k = 0; k < 3; ++k) Append(out, &mesh.normals[i][k], 4, swap);
    for (const auto& a : mesh.vertex_attributes) {
      if (as_byte(a)) {
        out.push_back(static_cast<char>(ColourByte(a.values[i])));
      } else {
        Append(out, &a.values[i], 4, swap);
      }
    }
  }
  for (const auto& f : mesh.faces) {
    out.push_back(3);
    for (uint32_t v : f) {
      const auto s = static_cast<int32_t>(v);
      Append(out, &s, 4, swap);
    }
  }
  return out;
}

}  // namespace lsqsurf::io
