#include "lsqsurf/v1/enum_names.h"

#include <cctype>

namespace lsqsurf::v1 {
namespace {

// "UpAxis" -> "UP_AXIS_": the prefix of the enum's value names.
std::string EnumPrefix(const google::protobuf::EnumDescriptor& type) {
  std::string out;
  for (char c : type.name()) {
    if (std::isupper(static_cast<unsigned char>(c)) && !out.empty()) out += '_';
    out += static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  }
  return out + "_";
}

}  // namespace

std::string EnumValueName(const google::protobuf::EnumDescriptor& type, std::string_view choice) {
  std::string out = EnumPrefix(type);
  for (char c : choice) out += static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  return out;
}

std::string ChoiceName(const google::protobuf::EnumValueDescriptor& value) {
  const std::string prefix = EnumPrefix(*value.type());
  std::string name = value.name();
  if (name.rfind(prefix, 0) == 0) name = name.substr(prefix.size());
  if (name == "UNSPECIFIED") return "";
  for (char& c : name) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return name;
}

}  // namespace lsqsurf::v1
