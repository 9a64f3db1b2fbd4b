#include "worker/io/ply.h"

#include <bit>
#include <cmath>
#include <cstring>
#include <optional>

#include "worker/core/strings.h"
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
    case Type::kInt8: case Type::kUint8: return 1;
    case Type::kInt16: case Type::kUint16: return 2;
    case Type::kInt32: case Type::kUint32: case Type::kFloat32: return 4;
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
class BodyReader {
 public:
  BodyReader(std::string_view body, PlyFormat format, size_t body_offset, size_t first_line)
      : body_(body), format_(format), body_offset_(body_offset), lines_(body),
        first_line_(first_line) {}

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
      case Type::kInt8: { int8_t v; std::memcpy(&v, raw, 1); out = v; break; }
      case Type::kUint8: { uint8_t v; std::memcpy(&v, raw, 1); out = v; break; }
      case Type::kInt16: { int16_t v; std::memcpy(&v, raw, 2); out = v; break; }
      case Type::kUint16: { uint16_t v; std::memcpy(&v, raw, 2); out = v; break; }
      case Type::kInt32: { int32_t v; std::memcpy(&v, raw, 4); out = v; break; }
      case Type::kUint32: { uint32_t v; std::memcpy(&v, raw, 4); out = v; break; }
      case Type::kFloat32: { float v; std::memcpy(&v, raw, 4); out = v; break; }
      case Type::kFloat64: { std::memcpy(&out, raw, 8); break; }
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

absl::StatusOr<core::TriangleMesh> ParsePly(std::string_view bytes, std::string_view name) {
  LineReader header(bytes);
  std::string_view line;
  if (!header.Next(line) || line != "ply") {
    return absl::InvalidArgumentError(core::StrCat(name, ": not a PLY file (no 'ply' magic)"));
  }
  std::optional<PlyFormat> format;
  std::vector<Element> elements;
  bool ended = false;
  while (header.Next(line)) {
    std::string_view rest = line;
    const std::string_view key = NextToken(rest);
    const size_t ln = header.line_number();
    if (key.empty() || key == "comment" || key == "obj_info") continue;
    if (key == "format") {
      const std::string_view f = NextToken(rest), version = NextToken(rest);
      if (f == "ascii") format = PlyFormat::kAscii;
      else if (f == "binary_little_endian") format = PlyFormat::kBinaryLittleEndian;
      else if (f == "binary_big_endian") format = PlyFormat::kBinaryBigEndian;
      else return HeaderError(name, ln, core::StrCat("unknown format '", f, "'"));
      if (version != "1.0") return HeaderError(name, ln, core::StrCat("unsupported version '", version, "'"));
    } else if (key == "element") {
      Element e;
      e.name = std::string(NextToken(rest));
      if (e.name.empty() || !ParseNumber(NextToken(rest), e.count)) {
        return HeaderError(name, ln, "expected 'element NAME COUNT'");
      }
      elements.push_back(std::move(e));
    } else if (key == "property") {
      if (elements.empty()) return HeaderError(name, ln, "property before any element");
      Property p;
      std::string_view t = NextToken(rest);
      if (t == "list") {
        p.is_list = true;
        const auto ct = ParseType(NextToken(rest));
        const std::string_view item = NextToken(rest);
        const auto it = ParseType(item);
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
      elements.back().properties.push_back(std::move(p));
    } else if (key == "end_header") {
      ended = true;
      break;
    } else {
      return HeaderError(name, ln, core::StrCat("unknown keyword '", key, "'"));
    }
  }
  if (!ended) return absl::InvalidArgumentError(core::StrCat(name, ": PLY header has no end_header"));
  if (!format) return absl::InvalidArgumentError(core::StrCat(name, ": PLY header has no format line"));

  const size_t body_offset = header.offset();
  BodyReader body(body_offset <= bytes.size() ? bytes.substr(body_offset) : std::string_view(),
                  *format, body_offset, header.line_number());
  core::TriangleMesh mesh;
  bool saw_vertex = false;
  for (const Element& e : elements) {
    // Every record takes at least one byte (binary) or two characters (ascii): a count larger
    // than that allows is a corrupt header, refused before any allocation.
    size_t min_record = 0;
    for (const Property& p : e.properties) min_record += p.is_list ? TypeSize(p.count_type) : TypeSize(p.type);
    if (*format == PlyFormat::kAscii) min_record = 2 * e.properties.size();
    if (min_record > 0 && e.count > body.remaining() / min_record) {
      return absl::InvalidArgumentError(core::StrCat(
          name, ": PLY element '", e.name, "' declares ", e.count,
          " records but the file is too short for them (truncated?)"));
    }
    const bool is_vertex = e.name == "vertex";
    const bool is_face = e.name == "face";
    int ix = -1, iy = -1, iz = -1, inx = -1, iny = -1, inz = -1, ilist = -1;
    std::vector<int> extra;  // Property index of each extra scalar attribute.
    for (size_t i = 0; i < e.properties.size(); ++i) {
      const Property& p = e.properties[i];
      const int idx = static_cast<int>(i);
      if (is_vertex && !p.is_list) {
        if (p.name == "x") ix = idx;
        else if (p.name == "y") iy = idx;
        else if (p.name == "z") iz = idx;
        else if (p.name == "nx") inx = idx;
        else if (p.name == "ny") iny = idx;
        else if (p.name == "nz") inz = idx;
        else extra.push_back(idx);
      }
      if (is_face && p.is_list && (p.name == "vertex_indices" || p.name == "vertex_index")) ilist = idx;
    }
    if (is_vertex) {
      if (saw_vertex) return absl::InvalidArgumentError(core::StrCat(name, ": two vertex elements"));
      saw_vertex = true;
      if (ix < 0 || iy < 0 || iz < 0) {
        return absl::InvalidArgumentError(core::StrCat(name, ": PLY vertex element lacks x, y or z"));
      }
      mesh.vertices.resize(e.count);
      const bool normals = inx >= 0 && iny >= 0 && inz >= 0;
      if (normals) mesh.normals.resize(e.count);
      for (int k : extra) {
        mesh.vertex_attributes.push_back({e.properties[static_cast<size_t>(k)].name, std::vector<float>(e.count)});
      }
    }
    if (is_face && ilist < 0) {
      return absl::InvalidArgumentError(core::StrCat(name, ": PLY face element has no vertex_indices list"));
    }
    std::vector<double> scalars(e.properties.size());
    std::vector<uint32_t> polygon;
    for (uint64_t r = 0; r < e.count; ++r) {
      if (!body.BeginRecord()) {
        return absl::InvalidArgumentError(core::StrCat(name, ": unexpected end of file in ", e.name, " ", r));
      }
      for (size_t i = 0; i < e.properties.size(); ++i) {
        const Property& p = e.properties[i];
        const std::string where = body.Where();
        if (!p.is_list) {
          if (!body.Read(p.type, scalars[i])) {
            return absl::InvalidArgumentError(core::StrCat(name, ": ", where, ": ", e.name, " ", r,
                                                           ": cannot read property '", p.name, "'"));
          }
          continue;
        }
        double count = 0;
        if (!body.Read(p.count_type, count) || count < 0 || count > 1e6) {
          return absl::InvalidArgumentError(core::StrCat(name, ": ", where, ": ", e.name, " ", r,
                                                         ": bad list length for '", p.name, "'"));
        }
        polygon.clear();
        for (int j = 0; j < static_cast<int>(count); ++j) {
          double v = 0;
          if (!body.Read(p.type, v)) {
            return absl::InvalidArgumentError(core::StrCat(name, ": ", body.Where(), ": ", e.name, " ", r,
                                                           ": list '", p.name, "' is cut short"));
          }
          if (static_cast<int>(i) == ilist) {
            if (v < 0 || v >= static_cast<double>(mesh.vertices.size()) || v != std::floor(v)) {
              return absl::InvalidArgumentError(core::StrCat(
                  name, ": ", where, ": face ", r, " refers to vertex ", v, " but there are ",
                  mesh.vertices.size(), " vertices"));
            }
            polygon.push_back(static_cast<uint32_t>(v));
          }
        }
        if (static_cast<int>(i) == ilist) {
          if (polygon.size() < 3) {
            return absl::InvalidArgumentError(core::StrCat(name, ": ", where, ": face ", r, " has fewer than 3 vertices"));
          }
          for (size_t j = 1; j + 1 < polygon.size(); ++j) {
            mesh.faces.push_back({polygon[0], polygon[j], polygon[j + 1]});
          }
        }
      }
      if (!body.EndRecord()) {
        return absl::InvalidArgumentError(core::StrCat(name, ": ", body.Where(), ": ", e.name, " ", r,
                                                       " has more values than the header declares"));
      }
      if (is_vertex) {
        auto& v = mesh.vertices[r];
        v = core::Vec3f(static_cast<float>(scalars[static_cast<size_t>(ix)]), static_cast<float>(scalars[static_cast<size_t>(iy)]),
                        static_cast<float>(scalars[static_cast<size_t>(iz)]));
        if (!mesh.normals.empty()) {
          mesh.normals[r] = core::Vec3f(static_cast<float>(scalars[static_cast<size_t>(inx)]), static_cast<float>(scalars[static_cast<size_t>(iny)]),
                                        static_cast<float>(scalars[static_cast<size_t>(inz)]));
        }
        for (size_t a = 0; a < extra.size(); ++a) {
          mesh.vertex_attributes[a].values[r] = static_cast<float>(scalars[static_cast<size_t>(extra[a])]);
        }
      }
    }
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
  for (const auto& a : mesh.vertex_attributes) core::StrAppend(&out, "property float ", a.name, "\n");
  if (!mesh.faces.empty()) {
    core::StrAppend(&out, "element face ", mesh.faces.size(), "\nproperty list uchar int vertex_indices\n");
  }
  out += "end_header\n";
  if (format == PlyFormat::kAscii) {
    for (size_t i = 0; i < mesh.vertices.size(); ++i) {
      const auto& v = mesh.vertices[i];
      std::vector<float> row = {v.x(), v.y(), v.z()};
      if (normals) row.insert(row.end(), {mesh.normals[i].x(), mesh.normals[i].y(), mesh.normals[i].z()});
      for (const auto& a : mesh.vertex_attributes) row.push_back(a.values[i]);
      for (size_t k = 0; k < row.size(); ++k) {
        if (k > 0) out.push_back(' ');
        internal::AppendFloat(out, row[k]);
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
    if (normals) for (int k = 0; k < 3; ++k) Append(out, &mesh.normals[i][k], 4, swap);
    for (const auto& a : mesh.vertex_attributes) Append(out, &a.values[i], 4, swap);
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
