#include <zlib.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstring>
#include <limits>
#include <pugixml.hpp>
#include <span>

#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/volume_cells.h"
#include "worker/io/volume_formats.h"

namespace lsqsurf::io {
namespace {

using core::Vec3d;
using core::VertexField;
using core::VolumeMesh;

// ---- VTK XML unstructured grids (.vtu) ----

int XmlTypeSize(std::string_view type) {
  if (type == "Int8" || type == "UInt8") return 1;
  if (type == "Int16" || type == "UInt16") return 2;
  if (type == "Int32" || type == "UInt32" || type == "Float32") return 4;
  if (type == "Int64" || type == "UInt64" || type == "Float64") return 8;
  return 0;
}

double LoadLittle(std::string_view type, const char* p) {
  auto load = [p]<class T>(T) {
    T v;
    std::memcpy(&v, p, sizeof(T));
    return static_cast<double>(v);
  };
  if (type == "Int8") return load(int8_t{});
  if (type == "UInt8") return load(uint8_t{});
  if (type == "Int16") return load(int16_t{});
  if (type == "UInt16") return load(uint16_t{});
  if (type == "Int32") return load(int32_t{});
  if (type == "UInt32") return load(uint32_t{});
  if (type == "Int64") return load(int64_t{});
  if (type == "UInt64") return load(uint64_t{});
  if (type == "Float32") return load(float{});
  return load(double{});
}

// Base64 without line breaks; whitespace is skipped. Errors on any other character.
absl::StatusOr<std::string> DecodeBase64(std::string_view text) {
  std::string out;
  out.reserve(text.size() * 3 / 4);
  uint32_t acc = 0;
  int bits = 0;
  for (char c : text) {
    int v;
    if (c >= 'A' && c <= 'Z')
      v = c - 'A';
    else if (c >= 'a' && c <= 'z')
      v = c - 'a' + 26;
    else if (c >= '0' && c <= '9')
      v = c - '0' + 52;
    else if (c == '+')
      v = 62;
    else if (c == '/')
      v = 63;
    else if (c == '=' || c == ' ' || c == '\n' || c == '\r' || c == '\t')
      continue;
    else
      return absl::InvalidArgumentError(core::StrCat("'", std::string(1, c), "' is not base64"));
    acc = (acc << 6) | static_cast<uint32_t>(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out += static_cast<char>((acc >> bits) & 0xff);
    }
  }
  return out;
}

// What the file's root says about binary data.
struct XmlLayout {
  int header_size = 4;        // UInt32 or UInt64 block headers.
  bool compressed = false;    // vtkZLibDataCompressor.
  std::string_view appended;  // The bytes after '_' in <AppendedData>, raw or base64.
  bool appended_base64 = false;
};

// Read as an integer, never through a double: a corrupt 64-bit size can exceed what a double
// converts back (undefined behaviour, found by fuzzing).
uint64_t HeaderInt(std::string_view bytes, size_t index, int size) {
  const auto* p = reinterpret_cast<const unsigned char*>(bytes.data() + index * static_cast<size_t>(size));
  uint64_t value = 0;
  for (int i = size - 1; i >= 0; --i) value = (value << 8) | p[i];
  return value;
}

// The bytes of one binary array: `header` then `payload`, inflated block by block when compressed.
absl::StatusOr<std::string> Unpack(std::string_view header, std::string_view payload, const XmlLayout& l,
                                   uint64_t max_bytes) {
  const int s = l.header_size;
  if (!l.compressed) {
    if (header.size() < static_cast<size_t>(s)) return absl::InvalidArgumentError("truncated array header");
    const uint64_t n = HeaderInt(header, 0, s);
    if (n > payload.size()) return absl::InvalidArgumentError("the array is shorter than its header says");
    return std::string(payload.substr(0, n));
  }
  if (header.size() < static_cast<size_t>(3 * s)) return absl::InvalidArgumentError("truncated compression header");
  const uint64_t blocks = HeaderInt(header, 0, s), block = HeaderInt(header, 1, s), last = HeaderInt(header, 2, s);
  if (header.size() < (3 + blocks) * s) return absl::InvalidArgumentError("truncated compression header");
  const uint64_t total = blocks == 0 ? 0 : (blocks - 1) * block + (last == 0 ? block : last);
  if (total > max_bytes) return absl::InvalidArgumentError("the array inflates past what its element count allows");
  std::string out(total, '\0');
  uint64_t in_pos = 0, out_pos = 0;
  for (uint64_t b = 0; b < blocks; ++b) {
    const uint64_t packed = HeaderInt(header, 3 + b, s);
    const uint64_t want = b + 1 == blocks && last != 0 ? last : block;
    if (in_pos + packed > payload.size()) return absl::InvalidArgumentError("a compressed block runs past the data");
    uLongf size = static_cast<uLongf>(want);
    if (uncompress(reinterpret_cast<Bytef*>(out.data() + out_pos), &size,
                   reinterpret_cast<const Bytef*>(payload.data() + in_pos), static_cast<uLong>(packed)) != Z_OK ||
        size != want) {
      return absl::InvalidArgumentError("a compressed block does not inflate");
    }
    in_pos += packed;
    out_pos += want;
  }
  return out;
}

// The header and payload of base64 text: compressed arrays encode the header separately.
absl::StatusOr<std::string> UnpackBase64(std::string_view text, const XmlLayout& l, uint64_t max_bytes) {
  size_t start = 0;
  while (start < text.size() && std::isspace(static_cast<unsigned char>(text[start]))) ++start;
  text.remove_prefix(start);
  if (!l.compressed) {
    LSQSURF_ASSIGN_OR_RETURN(std::string all, DecodeBase64(text));
    return Unpack(std::string_view(all).substr(0, l.header_size),
                  std::string_view(all).substr(std::min<size_t>(all.size(), static_cast<size_t>(l.header_size))), l,
                  max_bytes);
  }
  auto chars = [](size_t bytes) { return (bytes + 2) / 3 * 4; };
  LSQSURF_ASSIGN_OR_RETURN(std::string first, DecodeBase64(text.substr(0, chars(3 * l.header_size))));
  if (first.size() < static_cast<size_t>(l.header_size)) return absl::InvalidArgumentError("truncated header");
  const uint64_t blocks = HeaderInt(first, 0, l.header_size);
  if (blocks > (uint64_t{1} << 32)) return absl::InvalidArgumentError("impossible block count");
  const size_t header_chars = chars((3 + blocks) * l.header_size);
  if (header_chars > text.size()) return absl::InvalidArgumentError("truncated compression header");
  LSQSURF_ASSIGN_OR_RETURN(std::string header, DecodeBase64(text.substr(0, header_chars)));
  LSQSURF_ASSIGN_OR_RETURN(std::string payload, DecodeBase64(text.substr(header_chars)));
  return Unpack(header, payload, l, max_bytes);
}

// The values of a <DataArray> (ascii, binary or appended), `count` of them.
absl::StatusOr<std::vector<double>> ReadXmlArray(const pugi::xml_node& array, const XmlLayout& l, uint64_t count,
                                                 std::string_view what) {
  auto fail = [&](std::string_view why) { return absl::InvalidArgumentError(core::StrCat(what, ": ", why)); };
  const std::string_view type = array.attribute("type").value();
  const int size = XmlTypeSize(type);
  if (size == 0) return fail(core::StrCat("data type '", type, "' is not supported"));
  const std::string_view format = array.attribute("format").value();
  std::vector<double> out;
  if (format == "ascii") {
    std::string_view text = array.child_value();
    out.reserve(std::min<uint64_t>(count, text.size() / 2 + 1));
    size_t pos = 0;
    while (out.size() < count) {
      while (pos < text.size() && std::isspace(static_cast<unsigned char>(text[pos]))) ++pos;
      size_t end = pos;
      while (end < text.size() && !std::isspace(static_cast<unsigned char>(text[end]))) ++end;
      if (end == pos) return fail(core::StrCat("has ", out.size(), " values, ", count, " expected"));
      double v = 0;
      auto [p, ec] = std::from_chars(text.data() + pos, text.data() + end, v);
      if (ec != std::errc() || p != text.data() + end) {
        const std::string_view tok = text.substr(pos, end - pos);
        if (tok != "nan" && tok != "NaN") return fail(core::StrCat("'", tok, "' is not a number"));
        v = std::numeric_limits<double>::quiet_NaN();
      }
      out.push_back(v);
      pos = end;
    }
    return out;
  }
  const uint64_t bytes_needed = count * static_cast<uint64_t>(size);
  absl::StatusOr<std::string> raw = absl::UnknownError("");
  if (format == "binary") {
    raw = UnpackBase64(array.child_value(), l, bytes_needed);
  } else if (format == "appended") {
    const uint64_t offset = array.attribute("offset").as_ullong(UINT64_MAX);
    if (offset >= l.appended.size()) return fail("its offset lies outside <AppendedData>");
    const std::string_view rest = l.appended.substr(offset);
    if (l.appended_base64) {
      raw = UnpackBase64(rest, l, bytes_needed);
    } else if (!l.compressed) {
      raw = Unpack(rest.substr(0, l.header_size), rest.substr(std::min<size_t>(rest.size(), l.header_size)), l,
                   bytes_needed);
    } else {
      const uint64_t blocks = rest.size() >= static_cast<size_t>(l.header_size) ? HeaderInt(rest, 0, l.header_size) : 0;
      const size_t header = std::min<size_t>(rest.size(), (3 + std::min<uint64_t>(blocks, 1u << 30)) * l.header_size);
      raw = Unpack(rest.substr(0, header), rest.substr(header), l, bytes_needed);
    }
  } else {
    return fail(core::StrCat("format '", format, "' is not ascii, binary or appended"));
  }
  if (!raw.ok()) return fail(std::string(raw.status().message()));
  if (raw->size() < bytes_needed) {
    return fail(core::StrCat("holds ", raw->size() / size, " values, ", count, " expected (truncated?)"));
  }
  out.resize(count);
  for (uint64_t i = 0; i < count; ++i) out[i] = LoadLittle(type, raw->data() + i * size);
  return out;
}

}  // namespace

absl::StatusOr<VolumeMesh> ParseVtu(std::string_view bytes, std::string_view name) {
  auto fail = [&](std::string_view why) { return absl::InvalidArgumentError(core::StrCat(name, ": ", why)); };
  pugi::xml_document doc;
  // The appended section is binary after '_': parse only up to it, read it from the raw bytes.
  const size_t appended_tag = bytes.find("<AppendedData");
  XmlLayout layout;
  std::string xml(bytes.substr(0, appended_tag));
  if (appended_tag != std::string_view::npos) {
    const size_t underscore = bytes.find('_', appended_tag);
    const size_t close = bytes.rfind("</AppendedData>");
    if (underscore == std::string_view::npos || close == std::string_view::npos || close < underscore) {
      return fail("<AppendedData> without its '_' marker or closing tag");
    }
    const std::string_view tag = bytes.substr(appended_tag, underscore - appended_tag);
    layout.appended_base64 = tag.find("base64") != std::string_view::npos;
    layout.appended = bytes.substr(underscore + 1, close - underscore - 1);
    xml += "</VTKFile>";
  }
  const pugi::xml_parse_result parsed = doc.load_buffer(xml.data(), xml.size());
  if (!parsed)
    return fail(core::StrCat("not well-formed XML (", parsed.description(), " at byte ", parsed.offset, ")"));
  const pugi::xml_node root = doc.child("VTKFile");
  if (!root) return fail("no <VTKFile> root");
  if (std::string_view(root.attribute("type").value()) != "UnstructuredGrid") {
    return fail(core::StrCat("VTKFile type '", root.attribute("type").value(),
                             "' is not UnstructuredGrid (only .vtu grids are read)"));
  }
  if (std::string_view(root.attribute("byte_order").value()) == "BigEndian") {
    return fail("big-endian data is not supported; save the file little-endian");
  }
  layout.header_size = std::string_view(root.attribute("header_type").value()) == "UInt64" ? 8 : 4;
  const std::string_view compressor = root.attribute("compressor").value();
  if (!compressor.empty() && compressor != "vtkZLibDataCompressor") {
    return fail(core::StrCat("compressor ", compressor, " is not supported (use zlib or none)"));
  }
  layout.compressed = !compressor.empty();
  VolumeMesh mesh;
  for (pugi::xml_node piece : root.child("UnstructuredGrid").children("Piece")) {
    const uint64_t points = piece.attribute("NumberOfPoints").as_ullong(),
                   cells = piece.attribute("NumberOfCells").as_ullong();
    const auto base = static_cast<uint32_t>(mesh.positions.size());
    LSQSURF_ASSIGN_OR_RETURN(std::vector<double> xyz,
                             ReadXmlArray(piece.child("Points").child("DataArray"), layout, 3 * points, "Points"));
    for (uint64_t i = 0; i < points; ++i)
      mesh.positions.push_back(Vec3d(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]).cast<float>());
    pugi::xml_node connectivity, offsets, types;
    for (pugi::xml_node a : piece.child("Cells").children("DataArray")) {
      const std::string_view n = a.attribute("Name").value();
      if (n == "connectivity") connectivity = a;
      if (n == "offsets") offsets = a;
      if (n == "types") types = a;
    }
    if (cells > 0 && (!connectivity || !offsets || !types)) {
      return fail("<Cells> needs the arrays connectivity, offsets and types");
    }
    LSQSURF_ASSIGN_OR_RETURN(std::vector<double> ends, ReadXmlArray(offsets, layout, cells, "offsets"));
    LSQSURF_ASSIGN_OR_RETURN(std::vector<double> kinds, ReadXmlArray(types, layout, cells, "types"));
    const double total = cells == 0 ? 0 : ends.back();
    if (!(total >= 0 && total <= 8.0 * static_cast<double>(cells)))
      return fail("offsets: impossible connectivity size");
    LSQSURF_ASSIGN_OR_RETURN(std::vector<double> ids,
                             ReadXmlArray(connectivity, layout, static_cast<uint64_t>(total), "connectivity"));
    double begin = 0;
    std::vector<uint32_t> v;
    for (uint64_t c = 0; c < cells; ++c) {
      if (!(ends[c] >= begin && ends[c] <= total))
        return fail(core::StrCat("offsets: cell ", c, " ends before it begins"));
      v.clear();
      for (auto k = static_cast<size_t>(begin); k < static_cast<size_t>(ends[c]); ++k) {
        if (!(ids[k] >= 0 && ids[k] < static_cast<double>(points))) {
          return fail(core::StrCat("cell ", c, " refers to vertex ", ids[k], " of a piece with ", points));
        }
        v.push_back(base + static_cast<uint32_t>(ids[k]));
      }
      begin = ends[c];
      AppendCell(CellKind(kinds[c]), v, mesh);
    }
    for (pugi::xml_node a : piece.child("PointData").children("DataArray")) {
      const std::string field_name = a.attribute("Name").value();
      const int components = std::clamp(a.attribute("NumberOfComponents").as_int(1), 1, 9);
      LSQSURF_ASSIGN_OR_RETURN(std::vector<double> values,
                               ReadXmlArray(a, layout, points * components, core::StrCat("array '", field_name, "'")));
      VertexField* f = nullptr;
      for (VertexField& existing : mesh.fields) {
        if (existing.name == field_name) f = &existing;
      }
      if (f == nullptr) {
        if (base != 0) return fail(core::StrCat("array '", field_name, "' is missing from an earlier piece"));
        mesh.fields.push_back({field_name, components, {}});
        f = &mesh.fields.back();
      }
      f->values.insert(f->values.end(), values.begin(), values.end());
    }
  }
  if (mesh.positions.empty()) return fail("no <Piece> with points");
  if (absl::Status s = core::CheckVolumeStructure(mesh, core::kNoVolumeLimits); !s.ok()) {
    return fail(std::string(s.message()));
  }
  return mesh;
}

}  // namespace lsqsurf::io
