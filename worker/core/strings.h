// worker/core/strings.h — string concatenation that accepts std::string_view.
//
// Debian's abseil is built with its own string_view type, so absl::StrCat rejects
// std::string_view arguments; these helpers format through {fmt} instead. Floating-point
// values print in their shortest round-trip form.
#pragma once

#include <fmt/format.h>

#include <string>

#include "absl/strings/string_view.h"

// Lets {fmt} print abseil's string_view (e.g. `status.message()`).
template <>
struct fmt::formatter<absl::string_view> : fmt::formatter<fmt::string_view> {
  auto format(absl::string_view s, fmt::format_context& ctx) const {
    return fmt::formatter<fmt::string_view>::format(fmt::string_view(s.data(), s.size()), ctx);
  }
};

namespace lsqsurf::core {

template <class... Args>
std::string StrCat(const Args&... args) {
  std::string out;
  (fmt::format_to(std::back_inserter(out), "{}", args), ...);
  return out;
}

template <class... Args>
void StrAppend(std::string* out, const Args&... args) {
  (fmt::format_to(std::back_inserter(*out), "{}", args), ...);
}

}  // namespace lsqsurf::core
