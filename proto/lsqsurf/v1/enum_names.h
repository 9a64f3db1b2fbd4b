// proto/lsqsurf/v1/enum_names.h — how the API's enum values name a parameter's choices.
//
// A value is its enum type's name in UPPER_SNAKE case, an underscore, then the choice in upper
// case: the choice "uploaded" of `Interface` is INTERFACE_UPLOADED; the value numbered 0,
// <PREFIX>_UNSPECIFIED, means "the default". The server and the client both map by this rule.
#pragma once

#include <google/protobuf/descriptor.h>

#include <string>
#include <string_view>

namespace lsqsurf::v1 {

// ("Interface", "uploaded") -> "INTERFACE_UPLOADED".
std::string EnumValueName(const google::protobuf::EnumDescriptor& type, std::string_view choice);
// INTERFACE_UPLOADED -> "uploaded"; "" for the _UNSPECIFIED value.
std::string ChoiceName(const google::protobuf::EnumValueDescriptor& value);

}  // namespace lsqsurf::v1
