// client/generated_flags.h — command-line flags generated from a parameter message.
//
// One flag per field of a method's parameter message or of RenderOptions, named after the field
// (`support_factor` → `--support-factor`, plus any alias kept for the shorter names users know),
// typed after it (a flag for a bool, the choices for an enum), with the help, range and default
// of the server's descriptor table (generated at build time). Values are kept as given and set
// on the message by Apply(); the server checks the ranges, as it does for --param.
#pragma once

#include <google/protobuf/message.h>

#include <CLI/CLI.hpp>
#include <map>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"

namespace lsqsurf::cli {

// The table's text for one flag: its meaning, range and default.
struct FlagHelp {
  const char* section;  // A method's name, or "view" for the RenderOptions.
  const char* name;     // The field's.
  const char* help;
};

// The table's help of `name` in `section`, or "" when the table has no such field.
std::string TableHelp(std::string_view section, std::string_view name);

class GeneratedFlags {
 public:
  struct Naming {
    std::map<std::string, std::string> aliases{};  // Field → extra flag name, e.g. "fov_deg" → "--fov".
    std::set<std::string> only{};                  // When non-empty: these fields alone.
    std::set<std::string> skip{};                  // Fields with a hand-written flag, or none.
  };
  GeneratedFlags(std::string section, const google::protobuf::Descriptor& message)
      : section_(std::move(section)), message_(message) {}

  // Adds the flags to `cmd`; the object must stay where it is while `cmd` parses.
  void AddTo(CLI::App* cmd, const Naming& naming);
  // Sets every field given on `message` (of the descriptor's type). Errors: kInvalidArgument
  // naming the flag (a value of the wrong type).
  absl::Status Apply(google::protobuf::Message* message) const;
  bool empty() const { return given_.empty(); }

 private:
  std::string section_;
  const google::protobuf::Descriptor& message_;
  std::vector<std::pair<std::string, std::string>> given_;  // Field, value, in command-line order.
};

}  // namespace lsqsurf::cli
