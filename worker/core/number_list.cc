#include "worker/core/number_list.h"

#include <cstdlib>
#include <string>

#include "worker/core/strings.h"

namespace lsqsurf::core {

absl::StatusOr<std::vector<double>> ParseNumberList(std::string_view name, std::string_view text) {
  std::vector<double> out;
  size_t pos = 0;
  while (pos < text.size()) {
    if (text[pos] == ',' || text[pos] == ' ') {
      ++pos;
      continue;
    }
    size_t end = text.find_first_of(", ", pos);
    if (end == std::string_view::npos) end = text.size();
    const std::string item(text.substr(pos, end - pos));
    char* item_end = nullptr;
    const double v = std::strtod(item.c_str(), &item_end);
    if (*item_end != '\0') {
      return absl::InvalidArgumentError(
          StrCat(name, ": '", item, "' is not a number (give numbers separated by commas, e.g. 0.5,0.7)"));
    }
    out.push_back(v);
    pos = end;
  }
  return out;
}

}  // namespace lsqsurf::core
