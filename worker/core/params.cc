#include "worker/core/params.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdlib>

#include "worker/core/number_list.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::core {
namespace {

// Shortest text that reads back to the same double.
std::string Number(double v) {
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof(buf), v);
  return std::string(buf, static_cast<size_t>(r.ptr - buf));
}

// Text values are stored between ';' separators: escape '%', ';' and '=', and control bytes (a
// NUL would cut the stored text short, so that a job would come back after a restart as another).
std::string Escape(std::string_view text) {
  std::string out;
  for (char c : text) {
    if (c == '%' || c == ';' || c == '=' || static_cast<unsigned char>(c) < 0x20 || c == 0x7f) {
      StrAppend(&out, fmt::format("%{:02X}", static_cast<unsigned char>(c)));
    } else {
      out += c;
    }
  }
  return out;
}

std::string Unescape(std::string_view text) {
  std::string out;
  for (size_t i = 0; i < text.size(); ++i) {
    if (text[i] == '%' && i + 2 < text.size()) {
      out += static_cast<char>(std::strtol(std::string(text.substr(i + 1, 2)).c_str(), nullptr, 16));
      i += 2;
    } else {
      out += text[i];
    }
  }
  return out;
}

// "0.5,0.7": the list as Parse() and Decode() read it back.
std::string JoinNumbers(const std::vector<double>& values) {
  std::string out;
  for (double v : values) StrAppend(&out, out.empty() ? "" : ",", Number(v));
  return out;
}

}  // namespace

const char* ParamTypeName(ParamType type) {
  switch (type) {
    case ParamType::kReal: return "real";
    case ParamType::kInteger: return "integer";
    case ParamType::kFlag: return "flag";
    case ParamType::kChoice: return "choice";
    case ParamType::kText: return "text";
    case ParamType::kRealList: return "real list";
  }
  return "unknown";
}

const ParamChoice* ParamInfo::FindChoice(std::string_view choice_name) const {
  for (const auto& c : choices) {
    if (c.name == choice_name) return &c;
  }
  return nullptr;
}

const ParamChoice* ParamInfo::FindChoice(int value) const {
  for (const auto& c : choices) {
    if (c.value == value) return &c;
  }
  return nullptr;
}

bool ParamInfo::IsSpecial(double value) const {
  return std::any_of(special.begin(), special.end(), [&](const ParamSpecial& s) { return s.value == value; });
}

std::string ParamInfo::RangeText() const {
  switch (type) {
    case ParamType::kReal:
    case ParamType::kInteger:
    case ParamType::kRealList: {
      std::string specials;
      for (const ParamSpecial& s : special) StrAppend(&specials, Number(s.value), " (", s.meaning, "), ");
      if (!specials.empty()) specials.replace(specials.size() - 2, 2, " or ");
      const std::string interval = std::isinf(min_value) && std::isinf(max_value)
                                       ? std::string("any number")
                                       : StrCat("[", Number(min_value), ", ", Number(max_value), "]");
      const std::string values = StrCat(specials, interval, unit.empty() ? "" : " ", unit);
      return type == ParamType::kRealList ? StrCat("up to ", max_count, " values, each ", values) : values;
    }
    case ParamType::kFlag: return "true or false";
    case ParamType::kChoice: {
      std::string names;
      for (const auto& c : choices) StrAppend(&names, names.empty() ? "" : ", ", c.name);
      return StrCat("one of: ", names);
    }
    case ParamType::kText: return "text";
  }
  return "";
}

std::string ParamInfo::FormatValue(double value) const {
  if (type == ParamType::kFlag) return value != 0 ? "true" : "false";
  if (type == ParamType::kChoice) {
    const ParamChoice* c = FindChoice(static_cast<int>(value));
    return c ? c->name : Number(value);
  }
  return Number(value);
}

absl::Status CheckValue(const ParamInfo& info, double value) {
  auto fail = [&](std::string_view why) {
    return absl::InvalidArgumentError(
        StrCat(info.name, "=", info.FormatValue(value), " ", why, "; expected ", info.RangeText()));
  };
  if (!std::isfinite(value)) return fail("is not a finite number");
  if ((info.type == ParamType::kReal || info.type == ParamType::kInteger) && info.IsSpecial(value)) {
    return absl::OkStatus();
  }
  switch (info.type) {
    case ParamType::kInteger:
      if (value != std::floor(value)) return fail("is not a whole number");
      [[fallthrough]];
    case ParamType::kReal:
    case ParamType::kRealList:
      if (value < info.min_value || value > info.max_value) return fail("is out of range");
      return absl::OkStatus();
    case ParamType::kFlag:
      if (value != 0 && value != 1) return fail("is not a flag");
      return absl::OkStatus();
    case ParamType::kChoice:
      if (value != std::floor(value) || info.FindChoice(static_cast<int>(value)) == nullptr) {
        return fail("is not a known choice");
      }
      return absl::OkStatus();
    case ParamType::kText: return absl::OkStatus();
  }
  return absl::OkStatus();
}

absl::Status CheckList(const ParamInfo& info, const std::vector<double>& values) {
  if (values.size() > static_cast<size_t>(info.max_count)) {
    return absl::InvalidArgumentError(
        StrCat(info.name, " has ", values.size(), " values; it takes at most ", info.max_count));
  }
  for (size_t i = 0; i < values.size(); ++i) {
    if (absl::Status s = CheckValue(info, values[i]); !s.ok()) {
      return absl::InvalidArgumentError(StrCat("value ", i + 1, " of ", s.message()));
    }
  }
  return absl::OkStatus();
}

std::vector<ParamInfo> ParamSet::Describe() const { return holder_ ? holder_->Describe() : std::vector<ParamInfo>{}; }

const ParamInfo* ParamSet::Info(std::string_view name) const { return holder_ ? holder_->Info(name) : nullptr; }

absl::Status ParamSet::UnknownName(std::string_view name) const {
  std::string valid;
  for (const auto& p : Describe()) StrAppend(&valid, valid.empty() ? "" : ", ", p.name);
  return absl::InvalidArgumentError(
      StrCat("unknown parameter '", name, "'; valid parameters: ", valid.empty() ? "none" : valid));
}

absl::Status ParamSet::Set(std::string_view name, double value) {
  const ParamInfo* info = Info(name);
  if (info == nullptr) return UnknownName(name);
  if (info->type == ParamType::kText) return absl::InvalidArgumentError(StrCat(name, " takes text, not a number"));
  if (info->type == ParamType::kRealList) return SetList(name, {value});
  if (absl::Status s = CheckValue(*info, value); !s.ok()) return s;
  holder_->SetNumber(name, value);
  return absl::OkStatus();
}

absl::Status ParamSet::SetText(std::string_view name, std::string value) {
  const ParamInfo* info = Info(name);
  if (info == nullptr) return UnknownName(name);
  if (info->type != ParamType::kText) return Parse(name, value);
  if (value.size() > kMaxTextBytes) {
    return absl::InvalidArgumentError(
        StrCat(name, " has ", value.size(), " bytes; a text parameter takes at most ", kMaxTextBytes));
  }
  holder_->SetText(name, std::move(value));
  return absl::OkStatus();
}

absl::Status ParamSet::SetList(std::string_view name, std::vector<double> values) {
  const ParamInfo* info = Info(name);
  if (info == nullptr) return UnknownName(name);
  if (info->type != ParamType::kRealList) {
    if (values.size() != 1) return absl::InvalidArgumentError(StrCat(name, " takes one value, not a list"));
    return Set(name, values.front());
  }
  LSQSURF_RETURN_IF_ERROR(CheckList(*info, values));
  holder_->SetList(name, std::move(values));
  return absl::OkStatus();
}

absl::Status ParamSet::Parse(std::string_view name, std::string_view text) {
  const ParamInfo* info = Info(name);
  if (info == nullptr) return UnknownName(name);
  switch (info->type) {
    case ParamType::kText: return SetText(name, std::string(text));
    case ParamType::kRealList: {
      LSQSURF_ASSIGN_OR_RETURN(std::vector<double> values, ParseNumberList(name, text));
      return SetList(name, std::move(values));
    }
    case ParamType::kChoice:
      if (const ParamChoice* c = info->FindChoice(text)) return Set(name, c->value);
      return absl::InvalidArgumentError(
          StrCat(name, "='", text, "' is not a known choice; expected ", info->RangeText()));
    case ParamType::kFlag:
      if (text == "true" || text == "1") return Set(name, 1);
      if (text == "false" || text == "0") return Set(name, 0);
      return absl::InvalidArgumentError(StrCat(name, "='", text, "' is not a flag; expected true or false"));
    case ParamType::kReal:
    case ParamType::kInteger: {
      const std::string copy(text);
      char* end = nullptr;
      const double v = std::strtod(copy.c_str(), &end);
      if (copy.empty() || *end != '\0') {
        return absl::InvalidArgumentError(StrCat(name, "='", text, "' is not a number; expected ", info->RangeText()));
      }
      return Set(name, v);
    }
  }
  return absl::OkStatus();
}

std::optional<double> ParamSet::Get(std::string_view name) const {
  return holder_ ? holder_->GetNumber(name) : std::nullopt;
}

std::optional<std::string> ParamSet::GetText(std::string_view name) const {
  return holder_ ? holder_->GetText(name) : std::nullopt;
}

std::optional<std::vector<double>> ParamSet::GetList(std::string_view name) const {
  return holder_ ? holder_->GetList(name) : std::nullopt;
}

absl::Status ParamSet::Validate() const { return holder_ ? holder_->Validate() : absl::OkStatus(); }

std::string ParamSet::Encode() const {
  std::string out;
  for (const auto& p : Describe()) {
    if (p.type == ParamType::kText) {
      StrAppend(&out, p.name, "=", Escape(GetText(p.name).value_or("")), ";");
    } else if (p.type == ParamType::kRealList) {
      StrAppend(&out, p.name, "=", JoinNumbers(GetList(p.name).value_or(std::vector<double>{})), ";");
    } else {
      StrAppend(&out, p.name, "=", Number(Get(p.name).value_or(0)), ";");
    }
  }
  return out;
}

absl::Status ParamSet::Decode(std::string_view text) {
  while (!text.empty()) {
    const size_t end = text.find(';');
    const std::string_view item = text.substr(0, end);
    const size_t eq = item.find('=');
    if (eq != std::string_view::npos) {
      const std::string_view name = item.substr(0, eq), value = item.substr(eq + 1);
      if (const ParamInfo* info = Info(name)) {
        if (info->type == ParamType::kText) {
          holder_->SetText(name, Unescape(value));
        } else if (info->type == ParamType::kRealList) {
          LSQSURF_RETURN_IF_ERROR(Parse(name, value));
        } else {
          double v = 0;
          std::from_chars(value.data(), value.data() + value.size(), v);
          if (absl::Status s = Set(name, v); !s.ok()) return s;
        }
      }
    }
    if (end == std::string_view::npos) break;
    text.remove_prefix(end + 1);
  }
  return absl::OkStatus();
}

std::string ParamReferenceMarkdown(const std::vector<ParamInfo>& params) {
  std::string out = "| parameter | type | default | range | unit | meaning |\n|---|---|---|---|---|---|\n";
  for (const auto& p : params) {
    std::string def = p.FormatValue(p.default_value);
    if (p.type == ParamType::kText) def = StrCat("'", p.default_text, "'");
    if (p.type == ParamType::kRealList) def = p.default_list.empty() ? "none" : JoinNumbers(p.default_list);
    std::string meaning = p.help;
    if (p.type == ParamType::kChoice) {
      for (const auto& c : p.choices) StrAppend(&meaning, "<br>`", c.name, "`: ", c.help);
    }
    std::string range = p.RangeText();  // Without the unit, which has its own column.
    if (!p.unit.empty() && range.ends_with(" " + p.unit)) range.resize(range.size() - p.unit.size() - 1);
    StrAppend(&out, "| `", p.name, "` | ", ParamTypeName(p.type), " | ", def, " | ", range, " | ", p.unit, " | ",
              meaning, " |\n");
  }
  return out;
}

}  // namespace lsqsurf::core
