#include "worker/io/las.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <limits>

#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::io {
namespace {

constexpr size_t kHeader12 = 227;         // Versions 1.0 to 1.2.
constexpr size_t kHeader13 = 235;         // 1.3 adds the waveform start.
constexpr size_t kHeader14 = 375;         // 1.4 adds the extended counts.
constexpr uint64_t kColourSample = 4096;  // Records at the start, and as many spread, to tell 8- from 16-bit colour.
constexpr size_t kVlrHeader = 54, kEvlrHeader = 60;  // Variable-length records' headers (extended: 1.4's).
constexpr size_t kExtraDescriptor = 192;             // One extra bytes field's description.
constexpr size_t kMaxExtraAttributes = 64;           // Named extra fields kept; the others are skipped.

// Where a point format keeps what is read, and how long its record is at least.
struct PointLayout {
  uint32_t length;
  int rgb;        // Offset of red, green, blue (u16 each); -1: none.
  bool extended;  // Formats 6 to 10: classification in its own byte, flags beside it.
};

constexpr PointLayout kLayouts[11] = {
    {20, -1, false}, {28, -1, false}, {26, 20, false}, {34, 28, false}, {57, -1, false}, {63, 28, false},
    {30, -1, true},  {36, 30, true},  {38, 30, true},  {59, -1, true},  {67, 30, true},
};

template <typename T>
T Load(const char* p) {
  T v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

template <typename T>
void Store(std::string& out, size_t at, T v) {
  std::memcpy(out.data() + at, &v, sizeof v);
}

// A fixed-width text field of the header, up to its first NUL.
std::string Text(const char* p, size_t width) {
  const size_t n = std::find(p, p + width, '\0') - p;
  std::string s(p, n);
  for (char& c : s) {
    if (static_cast<unsigned char>(c) < 32 || static_cast<unsigned char>(c) > 126) c = '?';
  }
  return s;
}

// One field of the extra bytes after a format's own, as the Extra Bytes record describes it.
struct ExtraField {
  std::string name;  // The attribute's; empty: skipped.
  int type = 0;      // 1..10: uchar, char, ushort, short, ulong, long, ulonglong, longlong, float, double.
  uint32_t at = 0;   // Offset in the record.
  double scale = 1, offset = 0;
};

// The attributes every point format gives besides colour.
constexpr const char* kIntensity = "intensity";
constexpr const char* kClassification = "classification";

constexpr uint8_t kExtraTypeBytes[11] = {0, 1, 1, 2, 2, 4, 4, 8, 8, 4, 8};

double ExtraValue(const char* p, int type) {
  switch (type) {
    case 1: return Load<uint8_t>(p);
    case 2: return Load<int8_t>(p);
    case 3: return Load<uint16_t>(p);
    case 4: return Load<int16_t>(p);
    case 5: return Load<uint32_t>(p);
    case 6: return Load<int32_t>(p);
    case 7: return static_cast<double>(Load<uint64_t>(p));
    case 8: return static_cast<double>(Load<int64_t>(p));
    case 9: return Load<float>(p);
    default: return Load<double>(p);
  }
}

// An attribute name from a descriptor's: letters, digits and underscores (others become
// underscores), "extra_N" when none is left, and numbered on where it repeats one taken.
std::string ExtraName(std::string name, size_t field, const std::vector<std::string>& taken) {
  for (char& c : name) {
    if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
  }
  if (name.empty()) name = core::StrCat("extra_", field);
  std::string unique = name;
  for (int k = 2; std::find(taken.begin(), taken.end(), unique) != taken.end(); ++k)
    unique = core::StrCat(name, "_", k);
  return unique;
}

}  // namespace

struct LasReader::State {
  std::string name;
  std::string_view bytes;
  LasInfo info;
  PointLayout layout{};
  size_t data_begin = 0;
  uint64_t next = 0;

  absl::Status Error(std::string_view what) const { return absl::InvalidArgumentError(core::StrCat(name, ": ", what)); }
  std::vector<ExtraField> extras;  // Named ones only.

  absl::Status ParseHeader();
  // The Extra Bytes record (user LASF_Spec, id 4) among the variable-length records before the
  // points and, in 1.4, the extended ones after them; none is no error.
  absl::Status FindExtraBytes(size_t header_size, size_t data_offset);
  absl::Status ParseExtraBytes(std::string_view descriptors);
  const char* Record(uint64_t point) const { return bytes.data() + data_begin + point * info.record_length; }
  void ChooseColourDepth();
};

absl::Status LasReader::State::ParseHeader() {
  if (bytes.size() < kHeader12 || bytes.substr(0, 4) != "LASF") {
    return Error("not a LAS file (no LASF signature and 227-byte header)");
  }
  const char* h = bytes.data();
  const int major = static_cast<uint8_t>(h[24]), minor = static_cast<uint8_t>(h[25]);
  if (major != 1 || minor > 4) {
    return Error(core::StrCat("LAS version ", major, ".", minor, " is not 1.0 to 1.4"));
  }
  info.version_minor = minor;
  info.generating_software = Text(h + 58, 32);
  const uint16_t header_size = Load<uint16_t>(h + 94);
  const uint32_t data_offset = Load<uint32_t>(h + 96);
  const uint8_t format_byte = static_cast<uint8_t>(h[104]);
  info.record_length = Load<uint16_t>(h + 105);
  const size_t needed = minor >= 4 ? kHeader14 : minor == 3 ? kHeader13 : kHeader12;
  if (header_size < needed || header_size > bytes.size()) {
    return Error(core::StrCat("header size ", header_size, " is not between ", needed, " (LAS 1.", minor,
                              ") and the file's ", bytes.size(), " bytes"));
  }
  if (data_offset < header_size || data_offset > bytes.size()) {
    return Error(core::StrCat("offset to point data ", data_offset, " is not between the header's end (", header_size,
                              ") and the file's end (", bytes.size(), ")"));
  }
  if ((format_byte & 0xC0) != 0) {
    return Error(
        "the points are LAZ-compressed, which cannot be read here (no LAZ library in Debian 12); decompress "
        "the file first, e.g. with laszip -i in.laz -o out.las, or pdal translate in.laz out.las");
  }
  if (format_byte > 10) return Error(core::StrCat("point data format ", int{format_byte}, " is not 0 to 10"));
  info.point_format = format_byte;
  layout = kLayouts[format_byte];
  if (info.record_length < layout.length) {
    return Error(core::StrCat("point record length ", info.record_length, " is shorter than format ", int{format_byte},
                              "'s ", layout.length, " bytes"));
  }
  info.points = Load<uint32_t>(h + 107);
  if (minor >= 4) {
    // 1.4 writers leave the legacy count 0 for formats 6 to 10.
    if (const uint64_t extended = Load<uint64_t>(h + 247); extended != 0 || info.points == 0) info.points = extended;
  }
  const char* names = "XYZ";
  for (int a = 0; a < 3; ++a) {
    info.scale[a] = Load<double>(h + 131 + 8 * a);
    info.offset[a] = Load<double>(h + 155 + 8 * a);
    info.max[a] = Load<double>(h + 179 + 16 * a);
    info.min[a] = Load<double>(h + 187 + 16 * a);
    if (!std::isfinite(info.scale[a]) || info.scale[a] == 0 || std::abs(info.scale[a]) > 1e6) {
      return Error(core::StrCat(names[a], " scale factor ", info.scale[a], " is not a finite nonzero number"));
    }
    if (!std::isfinite(info.offset[a]) || std::abs(info.offset[a]) > 1e15) {
      return Error(core::StrCat(names[a], " offset ", info.offset[a], " is not a finite coordinate"));
    }
  }
  data_begin = data_offset;
  const uint64_t available = (bytes.size() - data_begin) / info.record_length;
  if (info.points > available) {
    return Error(core::StrCat("the header declares ", info.points, " points of ", info.record_length,
                              " bytes but the data holds only ", available));
  }
  // Float keeps about 7 digits: move the points near the origin when that would round away
  // the file's own quantum.
  double largest = 0, extent = 0, quantum = std::numeric_limits<double>::max();
  std::array<double, 3> centre{};
  for (int a = 0; a < 3; ++a) {
    double lo = info.min[a], hi = info.max[a];
    if (!std::isfinite(lo) || !std::isfinite(hi) || lo > hi || std::abs(lo) > 1e15 || std::abs(hi) > 1e15) {
      lo = hi = info.offset[a];  // A box that cannot be right: the offset is near the points too.
    }
    centre[a] = 0.5 * (lo + hi);
    largest = std::max({largest, std::abs(lo), std::abs(hi)});
    extent = std::max(extent, hi - lo);
    quantum = std::min(quantum, std::abs(info.scale[a]));
  }
  // Only a box far from the origin for its size gains by the move.
  if (largest > 4 * extent && largest * std::ldexp(1.0, -24) > 0.5 * quantum) {
    for (int a = 0; a < 3; ++a) info.shift[a] = std::round(centre[a]);
  }
  info.has_colour = layout.rgb >= 0;
  if (info.has_colour) ChooseColourDepth();
  return FindExtraBytes(header_size, data_offset);
}

absl::Status LasReader::State::FindExtraBytes(size_t header_size, size_t data_offset) {
  const char* h = bytes.data();
  auto is_extra_bytes = [](const char* record) {
    return Text(record + 2, 16) == "LASF_Spec" && Load<uint16_t>(record + 18) == 4;
  };
  // A chain that runs past its room (writers are not all careful) ends the walk, as it ended
  // before extra bytes were read: the points are still there.
  size_t at = header_size;
  for (uint32_t k = 0, count = Load<uint32_t>(h + 100); k < count && at + kVlrHeader <= data_offset; ++k) {
    const size_t length = Load<uint16_t>(bytes.data() + at + 20);
    if (at + kVlrHeader + length > data_offset) break;
    if (is_extra_bytes(bytes.data() + at)) return ParseExtraBytes(bytes.substr(at + kVlrHeader, length));
    at += kVlrHeader + length;
  }
  if (info.version_minor < 4) return absl::OkStatus();
  uint64_t evlr = Load<uint64_t>(h + 235);
  const uint32_t count = Load<uint32_t>(h + 243);
  for (uint32_t k = 0; k < count && evlr >= data_offset && evlr <= bytes.size() && bytes.size() - evlr >= kEvlrHeader;
       ++k) {
    const uint64_t length = Load<uint64_t>(bytes.data() + evlr + 20);
    if (length > bytes.size() - evlr - kEvlrHeader) break;
    if (is_extra_bytes(bytes.data() + evlr)) return ParseExtraBytes(bytes.substr(evlr + kEvlrHeader, length));
    evlr += kEvlrHeader + length;
  }
  return absl::OkStatus();
}

absl::Status LasReader::State::ParseExtraBytes(std::string_view descriptors) {
  const uint32_t room = info.record_length - layout.length;
  uint32_t at = layout.length;
  std::vector<std::string> taken(core::kColourChannels.begin(), core::kColourChannels.end());
  taken.insert(taken.end(), {kIntensity, kClassification});
  for (size_t field = 0; field < descriptors.size() / kExtraDescriptor; ++field) {
    const char* d = descriptors.data() + field * kExtraDescriptor;
    const int type = static_cast<uint8_t>(d[2]), options = static_cast<uint8_t>(d[3]);
    uint32_t size = 0;
    if (type == 0) {
      size = static_cast<uint32_t>(options);  // Undocumented bytes: the options byte counts them.
    } else if (type <= 10) {
      size = kExtraTypeBytes[type];
    } else if (type <= 30) {
      size = kExtraTypeBytes[(type - 11) % 10 + 1] * static_cast<uint32_t>((type - 11) / 10 + 2);  // Old arrays.
    } else {
      return Error(core::StrCat("extra bytes field ", field, " has data type ", type, ", not 0 to 30"));
    }
    if (at - layout.length + size > room) {
      return Error(core::StrCat("the extra bytes fields take more than the ", room,
                                " bytes each record has after point format ", info.point_format, "'s fields"));
    }
    if (type >= 1 && type <= 10 && extras.size() < kMaxExtraAttributes) {
      ExtraField& e = extras.emplace_back();
      e.name = ExtraName(Text(d + 4, 32), field, taken);
      taken.push_back(e.name);
      e.type = type;
      e.at = at;
      if ((options & 0x08) != 0) e.scale = Load<double>(d + 112);
      if ((options & 0x10) != 0) e.offset = Load<double>(d + 136);
      if (!std::isfinite(e.scale) || !std::isfinite(e.offset)) {
        return Error(core::StrCat("extra bytes field ", e.name, " has a scale or offset that is not a finite number"));
      }
    }
    at += size;
  }
  return absl::OkStatus();
}

// The standard scales colour to 16 bits; some writers store 0..255 in the fields. A sample of
// records with no channel above 255 (and some above 0) says the latter.
void LasReader::State::ChooseColourDepth() {
  bool any = false;
  const uint64_t head = std::min(info.points, kColourSample);
  const uint64_t stride = std::max<uint64_t>(1, info.points / kColourSample);
  auto look = [&](uint64_t p) {
    const char* rgb = Record(p) + layout.rgb;
    for (int c = 0; c < 3; ++c) {
      const uint16_t v = Load<uint16_t>(rgb + 2 * c);
      if (v > 255) return false;
      any = any || v > 0;
    }
    return true;
  };
  for (uint64_t p = 0; p < head; ++p) {
    if (!look(p)) return;
  }
  for (uint64_t p = head; p < info.points; p += stride) {
    if (!look(p)) return;
  }
  info.colour_8bit = any;
}

LasReader::LasReader(std::unique_ptr<State> state) : state_(std::move(state)) {}
LasReader::~LasReader() = default;

absl::StatusOr<std::unique_ptr<LasReader>> LasReader::Open(std::string_view bytes, std::string name) {
  auto state = std::make_unique<State>();
  state->name = std::move(name);
  state->bytes = bytes;
  LSQSURF_RETURN_IF_ERROR(state->ParseHeader());
  return std::unique_ptr<LasReader>(new LasReader(std::move(state)));
}

const LasInfo& LasReader::info() const { return state_->info; }
size_t LasReader::offset() const { return state_->data_begin + state_->next * state_->info.record_length; }

absl::Status LasReader::Read(size_t max_points, core::PointCloud& cloud) {
  State& s = *state_;
  LasInfo& info = s.info;
  if (cloud.attributes.empty()) {
    if (info.has_colour) {
      for (const char* n : core::kColourChannels) cloud.attributes.push_back({n, {}});
    }
    cloud.attributes.push_back({kIntensity, {}});
    cloud.attributes.push_back({kClassification, {}});
    for (const ExtraField& e : s.extras) cloud.attributes.push_back({e.name, {}});
  }
  const size_t first_scalar = info.has_colour ? 3 : 0;
  const float colour_scale = info.colour_8bit ? 1.0f : 1.0f / 257.0f;
  for (size_t kept = 0; kept < max_points && s.next < info.points;) {
    const char* r = s.Record(s.next++);
    const uint8_t flags = static_cast<uint8_t>(r[15]);
    const bool withheld = s.layout.extended ? (flags & 0x04) != 0 : (flags & 0x80) != 0;
    const int classification = s.layout.extended ? static_cast<uint8_t>(r[16]) : (flags & 0x1F);
    if (withheld) {
      ++info.withheld_points;
      continue;
    }
    if (classification == 7 || classification == 18) {
      ++info.noise_points;
      continue;
    }
    ++kept;
    core::Vec3f p;
    for (int a = 0; a < 3; ++a) {
      const double v = Load<int32_t>(r + 4 * a) * info.scale[a] + info.offset[a] - info.shift[a];
      p[a] = static_cast<float>(v);
    }
    cloud.positions.push_back(p);
    if (info.has_colour) {
      for (int c = 0; c < 3; ++c) {
        cloud.attributes[c].values.push_back(Load<uint16_t>(r + s.layout.rgb + 2 * c) * colour_scale);
      }
    }
    cloud.attributes[first_scalar].values.push_back(Load<uint16_t>(r + 12));
    cloud.attributes[first_scalar + 1].values.push_back(static_cast<float>(classification));
    for (size_t k = 0; k < s.extras.size(); ++k) {
      const ExtraField& e = s.extras[k];
      cloud.attributes[first_scalar + 2 + k].values.push_back(
          static_cast<float>(ExtraValue(r + e.at, e.type) * e.scale + e.offset));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<core::PointCloud> ParseLas(std::string_view bytes, std::string_view name, LasInfo* info) {
  auto reader = LasReader::Open(bytes, std::string(name));
  if (!reader.ok()) return reader.status();
  core::PointCloud cloud;
  LSQSURF_RETURN_IF_ERROR((*reader)->Read(std::numeric_limits<size_t>::max(), cloud));
  if (info != nullptr) *info = (*reader)->info();
  return cloud;
}

std::string EncodeLas(const core::PointCloud& cloud, const LasWriteOptions& options) {
  const int minor = options.version_minor >= 4 ? 4 : 2;
  const int format = std::clamp(options.point_format, 0, 10);
  const PointLayout layout = kLayouts[format];
  const size_t header = minor >= 4 ? kHeader14 : kHeader12;
  const size_t n = cloud.size();
  std::string out(header + n * layout.length, '\0');
  std::memcpy(out.data(), "LASF", 4);
  out[24] = 1;
  out[25] = static_cast<char>(minor);
  std::memcpy(out.data() + 26, "lsqsurf", 7);
  std::memcpy(out.data() + 58, "lsqsurf EncodeLas", 17);
  Store<uint16_t>(out, 94, static_cast<uint16_t>(header));
  Store<uint32_t>(out, 96, static_cast<uint32_t>(header));
  out[104] = static_cast<char>(format);
  Store<uint16_t>(out, 105, static_cast<uint16_t>(layout.length));
  if (format < 6) Store<uint32_t>(out, 107, static_cast<uint32_t>(n));
  if (minor >= 4) Store<uint64_t>(out, 247, n);
  core::Vec3d lo = core::Vec3d::Zero(), hi = core::Vec3d::Zero();
  for (size_t i = 0; i < n; ++i) {
    const core::Vec3d p = cloud.positions[i].cast<double>();
    lo = i == 0 ? p : core::Vec3d(lo.cwiseMin(p));
    hi = i == 0 ? p : core::Vec3d(hi.cwiseMax(p));
  }
  double scale = options.scale;
  if (!(scale > 0)) {
    const double largest = std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff());
    scale = largest > 0 ? std::pow(10.0, std::floor(std::log10(largest * std::ldexp(1.0, -24)))) : 1e-4;
    while ((hi - lo).maxCoeff() / scale > 2e9) scale *= 10;
  }
  for (int a = 0; a < 3; ++a) {
    Store<double>(out, 131 + 8 * a, scale);
    Store<double>(out, 155 + 8 * a, lo[a]);
    Store<double>(out, 179 + 16 * a, hi[a]);
    Store<double>(out, 187 + 16 * a, lo[a]);
  }
  const auto channel = core::ColourChannels(cloud.attributes, cloud.size());
  const core::ScalarAttribute *intensity = nullptr, *classification = nullptr;
  for (const core::ScalarAttribute& a : cloud.attributes) {
    if (a.values.size() != n) continue;
    if (a.name == "intensity") intensity = &a;
    if (a.name == "classification") classification = &a;
  }
  for (size_t i = 0; i < n; ++i) {
    const size_t at = header + i * layout.length;
    for (int a = 0; a < 3; ++a) {
      Store<int32_t>(out, at + 4 * a, static_cast<int32_t>(std::lround((cloud.positions[i][a] - lo[a]) / scale)));
    }
    if (intensity != nullptr) {
      Store<uint16_t>(out, at + 12,
                      static_cast<uint16_t>(std::clamp(std::round(intensity->values[i]), 0.0f, 65535.0f)));
    }
    out[at + 14] = 0x11;  // Return 1 of 1.
    if (classification != nullptr) {
      const auto c = static_cast<uint8_t>(std::clamp(std::round(classification->values[i]), 0.0f, 255.0f));
      out[at + (layout.extended ? 16 : 15)] = static_cast<char>(layout.extended ? c : (c & 0x1F));
    }
    if (layout.rgb >= 0 && channel[0] != nullptr) {
      for (int c = 0; c < 3; ++c) {
        const float v = std::clamp(std::round(channel[c]->values[i]), 0.0f, 255.0f) * 257.0f;
        Store<uint16_t>(out, at + layout.rgb + 2 * c, static_cast<uint16_t>(v));
      }
    }
  }
  return out;
}

}  // namespace lsqsurf::io
