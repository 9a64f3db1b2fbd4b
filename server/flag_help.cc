// lsqsurf-flag-help — writes the help of the command-line client's generated flags from the
// descriptor tables, as a C++ include, at build time: the client states each flag's meaning,
// range and default as the server checks them without linking an engine.
#include <cstdio>
#include <string>

#include "worker/core/params.h"
#include "worker/core/strings.h"
#include "worker/jobs/method_registry.h"

namespace {

using lsqsurf::core::StrAppend;

std::string CppString(const std::string& text) {
  std::string out = "\"";
  for (char c : text) {
    if (c == '"' || c == '\\') out += '\\';
    out += c == '\n' ? ' ' : c;
  }
  return out + "\"";
}

// "meaning; RANGE; default VALUE": what `lsqsurf CMD --help` shows beside a flag.
std::string HelpOf(const lsqsurf::core::ParamInfo& p) {
  std::string help = p.help;
  if (p.type != lsqsurf::core::ParamType::kText) StrAppend(&help, "; ", p.RangeText());
  switch (p.type) {
    case lsqsurf::core::ParamType::kText:
      if (!p.default_text.empty()) StrAppend(&help, "; default '", p.default_text, "'");
      break;
    case lsqsurf::core::ParamType::kRealList: break;
    default: StrAppend(&help, "; default ", p.FormatValue(p.default_value));
  }
  return help;
}

void Section(const std::string& section, const lsqsurf::core::ParamSet& params, std::string& out) {
  for (const auto& p : params.Describe()) {
    StrAppend(&out, "    {", CppString(section), ", ", CppString(p.name), ", ", CppString(HelpOf(p)), "},\n");
  }
}

}  // namespace

int main() {
  std::string out =
      "// Generated at build time from the descriptor tables by lsqsurf-flag-help; do not edit.\n"
      "inline constexpr FlagHelp kFlagHelp[] = {\n";
  for (const auto& m : lsqsurf::jobs::Methods()) Section(m.info.name, m.info.defaults, out);
  Section("view", lsqsurf::jobs::DefaultView(), out);
  out += "};\n";
  std::fputs(out.c_str(), stdout);
  return 0;
}
