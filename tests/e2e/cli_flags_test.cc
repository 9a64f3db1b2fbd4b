// The command-line client's generated flags: every parameter of the track table and every view
// option has a flag, whose help states the server's range and default, and values reach the
// message with their type checked before anything is sent.
#include <gtest/gtest.h>

#include <set>
#include <string>

#include "tests/e2e/harness.h"
#include "worker/jobs/method_registry.h"

namespace lsqsurf::testing {
namespace {

std::string FlagOf(const std::string& field) {
  std::string flag = "--" + field;
  for (char& c : flag) c = c == '_' ? '-' : c;
  return flag;
}

// The help line of `flag` in `help` (CLI11 may wrap the text onto the next line).
std::string HelpOf(const std::string& help, const std::string& flag) {
  for (size_t at = help.find(flag); at != std::string::npos; at = help.find(flag, at + 1)) {
    const char after = help[at + flag.size()];
    if (after != ' ' && after != ',' && after != '\n') continue;  // --marker-gap is not --marker-gap-x.
    // A flag's own line starts with its names; elsewhere it is named in another's help.
    const size_t line_start = help.rfind('\n', at) + 1;
    if (help.find_first_not_of(" ", line_start) != line_start + 2 || help[line_start + 2] != '-') continue;
    if (help.substr(line_start, at - line_start).find(' ', 2) != std::string::npos) continue;
    const size_t end = help.find("\n  -", at);
    return help.substr(at, end == std::string::npos ? std::string::npos : end - at);
  }
  return "";
}

void ExpectFlagsState(const std::string& help, const core::ParamSet& table, const std::set<std::string>& by_hand,
                      const char* what) {
  int checked = 0;
  for (const core::ParamInfo& p : table.Describe()) {
    if (by_hand.contains(p.name)) continue;
    const std::string line = HelpOf(help, FlagOf(p.name));
    ASSERT_FALSE(line.empty()) << what << ": no flag " << FlagOf(p.name) << " in\n" << help;
    if (p.type != core::ParamType::kText) {
      EXPECT_NE(line.find(p.RangeText()), std::string::npos) << what << ": " << line;
      EXPECT_NE(line.find("default " + p.FormatValue(p.default_value)), std::string::npos) << what << ": " << line;
    }
    ++checked;
  }
  EXPECT_GE(checked, 10) << what;
}

TEST(CliFlags, EveryTrackParameterAndViewOptionHasAFlagWithTheTablesRangeAndDefault) {
  const ClientRun track = Shell(std::string(LSQSURF_PATH) + " track --help");
  ASSERT_EQ(track.code, 0) << track.output;
  const jobs::MethodEntry* method = nullptr;
  for (const auto& m : jobs::Methods()) method = m.info.name == "track" ? &m : method;
  ASSERT_NE(method, nullptr);
  // The interface and field take a file too; h is a spacing; the volume drawing has its own.
  ExpectFlagsState(track.output, method->info.defaults, {"interface", "field"}, "track");
  ExpectFlagsState(track.output, jobs::DefaultView(),
                   {"volume_mode", "opacity", "iso_value", "volume_resolution", "ray_step"}, "view");
  const ClientRun render = Shell(std::string(LSQSURF_PATH) + " render --help");
  ASSERT_EQ(render.code, 0) << render.output;
  ExpectFlagsState(render.output, jobs::DefaultView(), {"volume_mode", "opacity", "iso_value"}, "render");
}

TEST(CliFlags, AValueOfTheWrongTypeIsRefusedBeforeAnythingIsSent) {
  // No server listens on the address: a refusal that names the flag shows nothing was sent.
  const std::string cli = std::string(LSQSURF_PATH) + " --server 127.0.0.1:1 ";
  const ClientRun steps = Shell(cli + "track --interface sphere --steps 2.5 -o /tmp/lsqsurf-never");
  EXPECT_EQ(steps.code, 3) << steps.output;
  EXPECT_NE(steps.output.find("--steps: steps='2.5' must be a whole number"), std::string::npos) << steps.output;
  const ClientRun choice = Shell(cli + "track --resampling sideways -o /tmp/lsqsurf-never");
  EXPECT_NE(choice.code, 0);
  EXPECT_NE(choice.output.find("markers"), std::string::npos) << choice.output;  // Lists the choices.
  const ClientRun number = Shell(cli + "render 0123 --azimuth east -o /tmp/lsqsurf-never.png");
  EXPECT_NE(number.code, 0);
  EXPECT_NE(number.output.find("--azimuth"), std::string::npos) << number.output;
}

}  // namespace
}  // namespace lsqsurf::testing
