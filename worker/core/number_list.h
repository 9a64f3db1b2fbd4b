// worker/core/number_list.h — the text form of a list of numbers, "0.5,0.7": how a list
// parameter is written on the command line (--param iso=0.5,0.7) and in the stored spec.
#pragma once

#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

namespace lsqsurf::core {

// Numbers separated by commas or spaces; an empty text is an empty list. Errors:
// kInvalidArgument naming `name` and the item that is not a number.
absl::StatusOr<std::vector<double>> ParseNumberList(std::string_view name, std::string_view text);

}  // namespace lsqsurf::core
