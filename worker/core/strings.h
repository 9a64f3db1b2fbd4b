// worker/core/strings.h — string concatenation that accepts std::string_view.
//
// Debian's abseil is built with its own string_view type, so absl::StrCat rejects
// std::string_view arguments; these helpers format through {fmt} instead. Floating-point
// values print in their shortest round-trip form.
#pragma once

#include <fmt/format.h>

#include <algorithm>
#include <string>
#include <string_view>

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

// `text` made safe to log or send back: control bytes (a newline that would forge a log line, a
// NUL that would cut it) written as \xNN, and at most `max_bytes` of it kept, the cut said.
inline std::string Printable(std::string_view text, size_t max_bytes = 1024) {
  std::string out;
  const size_t kept = std::min(text.size(), max_bytes);
  out.reserve(kept + 32);
  for (size_t i = 0; i < kept; ++i) {
    const auto c = static_cast<unsigned char>(text[i]);
    if (c < 0x20 || c == 0x7f) {
      StrAppend(&out, fmt::format("\\x{:02x}", c));
    } else {
      out += static_cast<char>(c);
    }
  }
  if (kept < text.size()) StrAppend(&out, "... (", text.size() - kept, " more bytes)");
  return out;
}

}  // namespace lsqsurf::core
