// The wire and the descriptor tables agree field by field, in both directions, and statuses
// keep their codes and messages.
#include "server/convert.h"

#include <google/protobuf/unknown_field_set.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <map>
#include <optional>
#include <set>
#include <sstream>
#include <tuple>

#include "lsqsurf/v1/enum_names.h"
#include "worker/jobs/method_registry.h"

namespace lsqsurf::server {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;

// Whether a proto field can carry a table field of this type.
bool Carries(const FieldDescriptor& f, core::ParamType type) {
  switch (type) {
    case core::ParamType::kReal: return f.cpp_type() == FieldDescriptor::CPPTYPE_DOUBLE;
    case core::ParamType::kInteger:
      return f.cpp_type() == FieldDescriptor::CPPTYPE_INT32 || f.cpp_type() == FieldDescriptor::CPPTYPE_INT64;
    case core::ParamType::kFlag: return f.cpp_type() == FieldDescriptor::CPPTYPE_BOOL;
    case core::ParamType::kChoice: return f.cpp_type() == FieldDescriptor::CPPTYPE_ENUM;
    case core::ParamType::kText: return f.cpp_type() == FieldDescriptor::CPPTYPE_STRING;
    case core::ParamType::kRealList: return f.cpp_type() == FieldDescriptor::CPPTYPE_DOUBLE;
  }
  return false;
}

// Every table field has a proto field of a matching type (and every choice its enum value,
// besides _UNSPECIFIED for "the default"), every field is `optional` so that unset means the
// default. Returns the names the message carries.
void ExpectMessageCarriesTable(const Descriptor& message, const std::vector<core::ParamInfo>& table,
                               const std::string& what) {
  for (const core::ParamInfo& p : table) {
    const FieldDescriptor* f = message.FindFieldByName(p.name);
    ASSERT_NE(f, nullptr) << what << ": " << message.name() << " has no field " << p.name;
    EXPECT_TRUE(Carries(*f, p.type)) << what << "." << p.name << " is a " << f->cpp_type_name();
    // Unset means the default: an `optional` field, or an empty repeated one for a list.
    if (p.type == core::ParamType::kRealList) {
      EXPECT_TRUE(f->is_repeated()) << what << "." << p.name << " must be repeated";
    } else {
      EXPECT_TRUE(f->has_presence()) << what << "." << p.name << " must be optional";
    }
    if (p.type != core::ParamType::kChoice) continue;
    EXPECT_NE(f->enum_type()->FindValueByNumber(0), nullptr);
    EXPECT_EQ(f->enum_type()->FindValueByNumber(0)->name(), v1::EnumValueName(*f->enum_type(), "unspecified"));
    EXPECT_EQ(f->enum_type()->value_count(), static_cast<int>(p.choices.size()) + 1) << what << "." << p.name;
    for (const auto& c : p.choices) {
      EXPECT_NE(f->enum_type()->FindValueByName(v1::EnumValueName(*f->enum_type(), c.name)), nullptr)
          << what << "." << p.name << " lacks " << c.name;
    }
  }
}

const Descriptor& MethodMessage(const std::string& method) {
  const FieldDescriptor* f = v1::JobSpec::descriptor()->FindFieldByName(method);
  EXPECT_NE(f, nullptr) << "JobSpec has no field " << method;
  EXPECT_EQ(f->containing_oneof(), v1::JobSpec::descriptor()->FindOneofByName("method"));
  return *f->message_type();
}

TEST(Convert, EveryMethodTableAndItsMessageAgree) {
  // Messages shared by several methods (ramls and apss) carry the union of their tables.
  std::map<const Descriptor*, std::set<std::string>> carried;
  for (const auto& m : jobs::Methods()) {
    const Descriptor& message = MethodMessage(m.info.name);
    const auto table = m.info.defaults.Describe();
    ExpectMessageCarriesTable(message, table, m.info.name);
    for (const auto& p : table) carried[&message].insert(p.name);
  }
  for (const auto& [message, names] : carried) {
    for (int i = 0; i < message->field_count(); ++i) {
      EXPECT_TRUE(names.contains(message->field(i)->name()))
          << message->name() << "." << message->field(i)->name() << " is no method's parameter";
    }
  }
  // And every method field of the oneof is a method.
  const auto* oneof = v1::JobSpec::descriptor()->FindOneofByName("method");
  for (int i = 0; i < oneof->field_count(); ++i) {
    EXPECT_NE(jobs::FindMethod(oneof->field(i)->name()), nullptr) << oneof->field(i)->name();
  }
}

TEST(Convert, RenderOptionsAndTheViewTableAgree) {
  const auto table = jobs::DefaultView().Describe();
  ExpectMessageCarriesTable(*v1::RenderOptions::descriptor(), table, "RenderOptions");
  EXPECT_EQ(v1::RenderOptions::descriptor()->field_count(), static_cast<int>(table.size()));
}

// Every parameter at a value other than its default (its bound, or another choice) survives
// the trip to the wire and back.
TEST(Convert, ParametersRoundTripThroughTheWire) {
  for (const auto& m : jobs::Methods()) {
    core::ParamSet changed = m.info.defaults;
    for (const auto& p : changed.Describe()) {
      switch (p.type) {
        case core::ParamType::kReal:
        case core::ParamType::kInteger:
          ASSERT_TRUE(changed.Set(p.name, p.default_value == p.max_value ? p.min_value : p.max_value).ok());
          break;
        case core::ParamType::kFlag: ASSERT_TRUE(changed.Set(p.name, 1 - p.default_value).ok()); break;
        case core::ParamType::kChoice: ASSERT_TRUE(changed.Set(p.name, p.choices.back().value).ok()); break;
        case core::ParamType::kText: ASSERT_TRUE(changed.SetText(p.name, "x").ok()); break;
        case core::ParamType::kRealList: {
          std::vector<double> values(static_cast<size_t>(p.max_count));
          for (size_t i = 0; i < values.size(); ++i) values[i] = 0.25 * static_cast<double>(i) - 1;
          ASSERT_TRUE(changed.SetList(p.name, values).ok());
          break;
        }
      }
    }
    v1::JobSpec wire;
    const FieldDescriptor* f = v1::JobSpec::descriptor()->FindFieldByName(m.info.name);
    ParamsToProto(changed, wire.GetReflection()->MutableMessage(&wire, f));
    core::ParamSet back = m.info.defaults;
    ASSERT_TRUE(FillParams(wire.GetReflection()->GetMessage(wire, f), &back).ok()) << m.info.name;
    EXPECT_EQ(back.Encode(), changed.Encode()) << m.info.name;
  }
}

TEST(Convert, UnsetFieldsKeepTheDefaults) {
  v1::JobSpec wire;
  wire.mutable_track()->set_steps(7);
  wire.mutable_track()->set_resampling(v1::TrackParams::RESAMPLING_GRIDLINES);
  auto spec = FromProto(wire);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->method, "track");
  EXPECT_EQ(spec->params.Get("steps"), 7);
  const core::ParamSet defaults = *jobs::DefaultParams("track");
  EXPECT_NE(spec->params.Get("resampling"), defaults.Get("resampling"));
  for (const char* unset : {"stride", "cells", "dt", "interface", "field", "marker_gap"}) {
    EXPECT_EQ(spec->params.Get(unset), defaults.Get(unset)) << unset;
  }
  EXPECT_FALSE(spec->preview.enabled);
  EXPECT_EQ(spec->mesh_position_bits, 0);  // Chosen per mesh.
}

TEST(Convert, RefusesWhatTheMethodDoesNotTake) {
  struct Case {
    const char* what;
    v1::JobSpec spec;
    const char* fragment;
  };
  std::vector<Case> cases(7);
  cases[0] = {"no method", {}, "names no method"};
  cases[1].what = "beta is APSS's";
  cases[1].spec.mutable_ramls()->set_beta(10);
  cases[1].fragment = "unknown parameter 'beta'";
  cases[2].what = "negative noise";
  cases[2].spec.mutable_pu()->set_noise_level(-0.5);
  cases[2].fragment = "noise_level=-0.5";
  cases[3].what = "not a choice";
  cases[3].spec.mutable_track()->set_field(static_cast<v1::TrackParams::Field>(9));
  cases[3].fragment = "field";
  cases[4].what = "a view out of range";
  cases[4].spec.mutable_iamls();
  cases[4].spec.mutable_preview()->mutable_options()->set_width(3);
  cases[4].fragment = "preview: width=3";
  // Fields of a newer proto are refused, not ignored (the job would run with the defaults).
  cases[5].what = "an unknown field in the method's message";
  // As a client built from another version sends them: bytes this proto does not describe.
  const auto add_unknown = [](google::protobuf::Message* m, int number, uint64_t value) {
    m->GetReflection()->MutableUnknownFields(m)->AddVarint(number, value);
  };
  add_unknown(cases[5].spec.mutable_iamls(), 999, 5);
  cases[5].fragment = "field number 999";
  cases[6].what = "unknown fields in the spec";
  cases[6].spec.mutable_iamls();
  add_unknown(&cases[6].spec, 900, 1);
  add_unknown(&cases[6].spec, 901, 2);
  cases[6].fragment = "field numbers 900, 901";
  for (const Case& c : cases) {
    auto spec = FromProto(c.spec);
    ASSERT_FALSE(spec.ok()) << c.what;
    EXPECT_EQ(spec.status().code(), absl::StatusCode::kInvalidArgument) << c.what;
    EXPECT_NE(spec.status().message().find(c.fragment), std::string_view::npos) << c.what << ": " << spec.status();
  }
}

TEST(Convert, StatusCodesAndMessagesPassThrough) {
  for (int code = 1; code <= 16; ++code) {
    const absl::Status s(static_cast<absl::StatusCode>(code), "what to fix");
    const grpc::Status g = ToGrpcStatus(s);
    EXPECT_EQ(static_cast<int>(g.error_code()), code);
    EXPECT_EQ(g.error_message(), "what to fix");
  }
  EXPECT_TRUE(ToGrpcStatus(absl::OkStatus()).ok());
}

TEST(Convert, EveryJobStateHasItsOwnWireValue) {
  std::set<int> seen;
  for (auto s : {jobs::JobState::kQueued, jobs::JobState::kRunning, jobs::JobState::kSucceeded, jobs::JobState::kFailed,
                 jobs::JobState::kCancelled}) {
    const v1::JobState wire = ToProto(s);
    EXPECT_NE(wire, v1::JOB_STATE_UNSPECIFIED);
    EXPECT_TRUE(seen.insert(wire).second);
    // The display names agree too (the CLI prints the wire's, the logs the job layer's).
    EXPECT_EQ(v1::JobState_Name(wire), v1::EnumValueName(*v1::JobState_descriptor(), jobs::JobStateName(s)));
  }
}

TEST(Convert, ListedParametersDescribeTheirTables) {
  for (const auto& m : jobs::Methods()) {
    for (const auto& p : m.info.defaults.Describe()) {
      v1::Parameter wire;
      ToProto(p, &wire);
      EXPECT_EQ(wire.name(), p.name);
      EXPECT_EQ(wire.default_value(), p.default_value) << m.info.name << "." << p.name;
      EXPECT_EQ(wire.choices_size(), static_cast<int>(p.choices.size()));
      EXPECT_EQ(wire.special_values_size(), static_cast<int>(p.special.size()));
      // A default outside the range is one of the special values (0 = chosen, -1 = estimated).
      if ((p.type == core::ParamType::kReal || p.type == core::ParamType::kInteger) && !p.IsSpecial(p.default_value)) {
        EXPECT_LE(wire.min_value(), wire.default_value()) << m.info.name << "." << p.name;
        EXPECT_GE(wire.max_value(), wire.default_value()) << m.info.name << "." << p.name;
      }
    }
  }
}

// A client that checks values against ListMethods alone (the range, or one of the special
// values) accepts exactly what the server's tables accept: probed at the ends of each range,
// just outside them, at every special value and next to it, and in between.
TEST(Convert, AClientValidatingFromTheListingAgreesWithTheServer) {
  int probed = 0;
  for (const auto& m : jobs::Methods()) {
    for (const auto& p : m.info.defaults.Describe()) {
      if (p.type != core::ParamType::kReal && p.type != core::ParamType::kInteger) continue;
      v1::Parameter wire;
      ToProto(p, &wire);
      const auto listed_valid = [&](double v) {
        if (v >= wire.min_value() && v <= wire.max_value() && (!wire.integer() || v == std::floor(v))) return true;
        for (const auto& special : wire.special_values()) {
          if (special.value() == v) return true;
        }
        return false;
      };
      const double step = wire.integer() ? 1.0 : std::max(1e-9, 1e-3 * (wire.max_value() - wire.min_value()));
      std::vector<double> values = {wire.min_value(), wire.max_value(), 0.5 * (wire.min_value() + wire.max_value()),
                                    wire.min_value() - step, wire.max_value() + step};
      for (const auto& special : wire.special_values()) {
        values.insert(values.end(), {special.value(), special.value() - step, special.value() + step});
      }
      for (double v : values) {
        core::ParamSet set = m.info.defaults;
        const absl::Status accepted = set.Set(p.name, v);
        EXPECT_EQ(accepted.ok(), listed_valid(v)) << m.info.name << "." << p.name << "=" << v << ": " << accepted;
        ++probed;
      }
    }
  }
  EXPECT_GT(probed, 500);
}

// The same for list parameters: a count up to max_count, each value finite and within the bounds.
TEST(Convert, AClientValidatingAListFromTheListingAgreesWithTheServer) {
  int probed = 0;
  for (const auto& m : jobs::Methods()) {
    for (const auto& p : m.info.defaults.Describe()) {
      if (p.type != core::ParamType::kRealList) continue;
      v1::Parameter wire;
      ToProto(p, &wire);
      ASSERT_EQ(wire.type(), v1::Parameter::TYPE_REAL_LIST);
      ASSERT_GT(wire.max_count(), 0);
      const auto listed_valid = [&](const std::vector<double>& values) {
        if (static_cast<int>(values.size()) > wire.max_count()) return false;
        return std::all_of(values.begin(), values.end(), [&](double v) {
          return std::isfinite(v) && v >= wire.min_value() && v <= wire.max_value();
        });
      };
      const auto count = static_cast<size_t>(wire.max_count());
      for (const std::vector<double>& values :
           {std::vector<double>{}, std::vector<double>(count, 0.5), std::vector<double>(count + 1, 0.5),
            std::vector<double>{-1e300, 1e300}, std::vector<double>{0, std::nan("")},
            std::vector<double>{std::numeric_limits<double>::infinity()}}) {
        core::ParamSet set = m.info.defaults;
        const absl::Status accepted = set.SetList(p.name, values);
        EXPECT_EQ(accepted.ok(), listed_valid(values))
            << m.info.name << "." << p.name << " with " << values.size() << " values: " << accepted;
        ++probed;
      }
    }
  }
  EXPECT_GE(probed, 6);  // Volume's iso at least.
}

// The proto's comments state each field's default, "(default X)", and each enum's
// "_UNSPECIFIED = 0;  // The default: NAME.": they must be the tables' defaults. Returns, per
// message, field name -> the stated default.
// The words of a proto line before its comment, and the comment.
std::pair<std::vector<std::string>, std::string> SplitProtoLine(const std::string& line) {
  const size_t slash = line.find("//");
  std::istringstream code(line.substr(0, slash));
  std::vector<std::string> words;
  for (std::string w; code >> w;) words.push_back(w);
  return {words, slash == std::string::npos ? "" : line.substr(slash + 2)};
}

// What follows `marker` in `comment` up to the first of `ends`, or empty.
std::string After(const std::string& comment, const std::string& marker, const std::string& ends) {
  const size_t at = comment.find(marker);
  if (at == std::string::npos) return "";
  const std::string rest = comment.substr(at + marker.size());
  return rest.substr(0, rest.find_first_of(ends));
}

// Per message, the type and comment of each optional field; per enum, its stated default.
struct ProtoComments {
  std::map<std::string, std::map<std::string, std::pair<std::string, std::string>>> fields;
  std::map<std::string, std::string> enum_default;
};

ProtoComments ReadProtoComments() {
  std::ifstream in(LSQSURF_SOURCE_DIR "/proto/lsqsurf/v1/reconstruction.proto");
  EXPECT_TRUE(in.good());
  ProtoComments out;
  std::vector<std::string> scopes;  // Enclosing message and enum names.
  for (std::string line; std::getline(in, line);) {
    const auto [words, comment] = SplitProtoLine(line);
    if (words.size() >= 3 && (words[0] == "message" || words[0] == "enum") && words[2] == "{") {
      scopes.push_back(words[1]);
    } else if (!words.empty() && words[0] == "}" && !scopes.empty()) {
      scopes.pop_back();
    } else if (!scopes.empty() && !words.empty() && words[0].ends_with("_UNSPECIFIED")) {
      if (auto d = After(comment, "The default: ", "."); !d.empty()) out.enum_default[scopes.back()] = d;
    } else if (!scopes.empty() && words.size() >= 3 && words[0] == "optional") {
      out.fields[scopes.back()][words[2]] = {words[1], comment};
    }
  }
  return out;
}

std::map<std::string, std::map<std::string, std::string>> StatedDefaults() {
  const ProtoComments proto = ReadProtoComments();
  std::map<std::string, std::map<std::string, std::string>> out;
  for (const auto& [message, fields] : proto.fields) {
    for (const auto& [field, typed] : fields) {
      const auto& [type, comment] = typed;
      if (auto d = After(comment, "(default ", "),"); !d.empty()) out[message][field] = d;
      if (auto e = proto.enum_default.find(type); e != proto.enum_default.end()) out[message][field] = e->second;
    }
  }
  return out;
}

// The first range "A..B" in a comment: two numbers joined by two dots.
std::optional<std::pair<double, double>> RangeIn(const std::string& comment) {
  const auto numeric = [](char c) { return std::isdigit(static_cast<unsigned char>(c)) || std::strchr(".e+-", c); };
  for (size_t dots = comment.find(".."); dots != std::string::npos; dots = comment.find("..", dots + 2)) {
    size_t begin = dots;
    while (begin > 0 && numeric(comment[begin - 1])) --begin;
    const std::string left = comment.substr(begin, dots - begin);
    const char* right = comment.c_str() + dots + 2;
    char* end = nullptr;
    const double high = std::strtod(right, &end);
    if (left.empty() || end == right || !(std::isdigit(static_cast<unsigned char>(left[0])) || left[0] == '-')) {
      continue;
    }
    return std::pair{std::stod(left), high};
  }
  return std::nullopt;
}

// Per message, field name -> the range its comment states as "A..B".
std::map<std::string, std::map<std::string, std::pair<double, double>>> StatedRanges() {
  std::map<std::string, std::map<std::string, std::pair<double, double>>> out;
  for (const auto& [message, fields] : ReadProtoComments().fields) {
    for (const auto& [field, typed] : fields) {
      if (auto range = RangeIn(typed.second)) out[message][field] = *range;
    }
  }
  return out;
}

void ExpectStatedDefaultsMatch(const std::map<std::string, std::string>& stated,
                               const std::vector<core::ParamInfo>& table, const std::string& what) {
  for (const core::ParamInfo& p : table) {
    auto it = stated.find(p.name);
    if (it == stated.end()) continue;
    const std::string& text = it->second;
    switch (p.type) {
      case core::ParamType::kFlag:
        EXPECT_EQ(text, p.default_value != 0 ? "true" : "false") << what << "." << p.name;
        break;
      case core::ParamType::kChoice: {
        const core::ParamChoice* c = p.FindChoice(static_cast<int>(p.default_value));
        ASSERT_NE(c, nullptr);
        std::string upper;
        for (char ch : c->name) upper += static_cast<char>(std::toupper(static_cast<unsigned char>(ch)));
        EXPECT_EQ(text, upper) << what << "." << p.name;
        break;
      }
      case core::ParamType::kText:
      case core::ParamType::kRealList: break;
      default: {
        const std::string number = text.substr(0, text.find_first_of(" :"));
        EXPECT_NEAR(std::stod(number), p.default_value, 1e-12 * std::abs(p.default_value))
            << what << "." << p.name << ": the proto says " << text;
      }
    }
  }
}

TEST(Convert, TheProtoStatesTheTablesDefaults) {
  const auto stated = StatedDefaults();
  size_t checked = 0;
  for (const auto& m : jobs::Methods()) {
    const std::string message = MethodMessage(m.info.name).name();
    ASSERT_TRUE(stated.contains(message)) << message;
    ExpectStatedDefaultsMatch(stated.at(message), m.info.defaults.Describe(), m.info.name);
    checked += stated.at(message).size();
  }
  ASSERT_TRUE(stated.contains("RenderOptions"));
  ExpectStatedDefaultsMatch(stated.at("RenderOptions"), jobs::DefaultView().Describe(), "RenderOptions");
  EXPECT_GT(checked, 40u);  // The parser found the comments.
}

// A range a proto comment states ("0.05..3") is the table's: comments do not drift from the one
// description, and ListMethods says the same as the proto.
TEST(Convert, TheProtoStatesTheTablesRanges) {
  const auto stated = StatedRanges();
  size_t checked = 0;
  const auto expect_ranges = [&](const std::map<std::string, std::pair<double, double>>& ranges,
                                 const std::vector<core::ParamInfo>& table, const std::string& what) {
    for (const core::ParamInfo& p : table) {
      auto it = ranges.find(p.name);
      if (it == ranges.end() || (p.type != core::ParamType::kReal && p.type != core::ParamType::kInteger)) continue;
      EXPECT_NEAR(it->second.first, p.min_value, 1e-12 * std::abs(p.min_value)) << what << "." << p.name;
      EXPECT_NEAR(it->second.second, p.max_value, 1e-12 * std::abs(p.max_value)) << what << "." << p.name;
      ++checked;
    }
  };
  for (const auto& m : jobs::Methods()) {
    const std::string message = MethodMessage(m.info.name).name();
    if (stated.contains(message)) expect_ranges(stated.at(message), m.info.defaults.Describe(), m.info.name);
  }
  if (stated.contains("RenderOptions")) {
    expect_ranges(stated.at("RenderOptions"), jobs::DefaultView().Describe(), "RenderOptions");
  }
  EXPECT_GT(checked, 50u);  // The parser found the ranges.
}

}  // namespace
}  // namespace lsqsurf::server
