#include "client/generated_flags.h"

#include "client/client.h"
#include "lsqsurf/v1/enum_names.h"
#include "worker/core/strings.h"

namespace lsqsurf::cli {
namespace {

#include "client/flag_help.inc"

using google::protobuf::FieldDescriptor;

std::string FlagName(const std::string& field) {
  std::string name = "--" + field;
  for (char& c : name) c = c == '_' ? '-' : c;
  return name;
}

}  // namespace

std::string TableHelp(std::string_view section, std::string_view name) {
  for (const FlagHelp& h : kFlagHelp) {
    if (section == h.section && name == h.name) return h.help;
  }
  return "";
}

void GeneratedFlags::AddTo(CLI::App* cmd, const Naming& naming) {
  for (int i = 0; i < message_.field_count(); ++i) {
    const FieldDescriptor& f = *message_.field(i);
    const std::string& field = f.name();
    if (naming.skip.contains(field) || (!naming.only.empty() && !naming.only.contains(field))) continue;
    std::string names = FlagName(field);
    if (auto alias = naming.aliases.find(field); alias != naming.aliases.end()) {
      names = core::StrCat(alias->second, ",", names);
    }
    const std::string help = TableHelp(section_, field);
    if (f.cpp_type() == FieldDescriptor::CPPTYPE_BOOL) {
      // `--meshes` sets it, `--meshes=false` clears it.
      cmd->add_flag_function(
          names, [this, field](int64_t count) { given_.emplace_back(field, count > 0 ? "true" : "false"); }, help);
      continue;
    }
    CLI::Option* option = cmd->add_option_function<std::string>(
        names, [this, field](const std::string& value) { given_.emplace_back(field, value); }, help);
    if (f.cpp_type() == FieldDescriptor::CPPTYPE_ENUM) {
      std::vector<std::string> choices;
      for (int v = 0; v < f.enum_type()->value_count(); ++v) {
        if (std::string choice = v1::ChoiceName(*f.enum_type()->value(v)); !choice.empty()) choices.push_back(choice);
      }
      option->type_name("CHOICE")->check(CLI::IsMember(choices));
    } else if (f.cpp_type() == FieldDescriptor::CPPTYPE_STRING) {
      option->type_name("TEXT");
    } else if (f.is_repeated()) {
      option->type_name("NUMBERS");  // Separated by commas.
    } else {
      const bool whole =
          f.cpp_type() != FieldDescriptor::CPPTYPE_DOUBLE && f.cpp_type() != FieldDescriptor::CPPTYPE_FLOAT;
      CLI::Validator number = CLI::Number;
      option->type_name(whole ? "INT" : "FLOAT")->check(number.description(""));
    }
  }
}

absl::Status GeneratedFlags::Apply(google::protobuf::Message* message) const {
  for (const auto& [field, value] : given_) {
    if (absl::Status s = client::SetMessageField(message, field, value); !s.ok()) {
      return absl::InvalidArgumentError(core::StrCat(FlagName(field), ": ", s.message()));
    }
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::cli
