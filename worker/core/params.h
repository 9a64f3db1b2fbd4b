// worker/core/params.h — one descriptor table per parameter struct.
//
// A parameter's name, type, default, range, unit and help are written once, in the table that
// sits beside its struct (e.g. `pu::PuParamTable()` beside `pu::PuParams`). Everything else is
// derived from the table: the engine's `Validate()`, the service's method listing, the
// conversion from the wire (by field name), the CLI's help, the stored form of a job's
// parameters and the generated parameter reference. Defaults are the struct's member
// initializers, read from a default-constructed struct, so they too exist once.
//
// Tables are built once (function-local statics) and are immutable afterwards: reading them
// from many threads is safe.
#pragma once

#include <algorithm>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <typeinfo>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "worker/core/status.h"

namespace lsqsurf::core {

enum class ParamType {
  kReal,      // A finite number within [min_value, max_value].
  kInteger,   // A whole number within [min_value, max_value].
  kFlag,      // 0 or 1 (false / true).
  kChoice,    // One of `choices`, by name on the wire and in text, by value in the struct.
  kText,      // A string (e.g. a vertex attribute's name).
  kRealList,  // Up to `max_count` finite numbers, each within [min_value, max_value].
};

const char* ParamTypeName(ParamType type);

struct ParamChoice {
  std::string name;  // lower_snake_case, e.g. "markers".
  int value = 0;     // The enum's value in the struct (stored job specs keep it: never renumber).
  std::string help;
};

// A value outside a number's range that is accepted with a meaning of its own, such as
// 0 = chosen by the engine.
struct ParamSpecial {
  double value = 0;
  std::string meaning;  // "chosen from the noise".
};

// Everything a user or a tool needs to know about one parameter.
struct ParamInfo {
  std::string name{};
  ParamType type = ParamType::kReal;
  double default_value = 0;             // Numbers, flags (0/1) and choices (the value).
  std::string default_text{};           // kText only.
  std::vector<double> default_list{};   // kRealList only.
  double min_value = 0, max_value = 0;  // Inclusive; kReal, kInteger and each of a kRealList.
  std::string unit{};                   // Empty for dimensionless values.
  std::string help{};                   // Meaning; the range and unit are not repeated in it.
  std::vector<ParamChoice> choices{};   // kChoice only.
  std::vector<ParamSpecial> special{};  // kReal and kInteger: accepted besides [min_value, max_value].
  int max_count = 0;                    // kRealList: the most values it takes.

  // The choice called `name` / with `value`, or nullptr.
  const ParamChoice* FindChoice(std::string_view choice_name) const;
  const ParamChoice* FindChoice(int value) const;
  bool IsSpecial(double value) const;
  // "[1e-06, 0.1] share of the diagonal", "0 (chosen) or [0.05, 3]", "one of: markers, gridlines",
  // "up to 16 values, each any number".
  std::string RangeText() const;
  // The value as a user writes it: a number, true/false, or a choice's name.
  std::string FormatValue(double value) const;
};

// Checks one value against its description; the message names the parameter and its range.
absl::Status CheckValue(const ParamInfo& info, double value);
// Checks a kRealList's values: their count and each value.
absl::Status CheckList(const ParamInfo& info, const std::vector<double>& values);

// The table of a parameter struct P. Fields are added in the order users should read them.
template <class P>
class ParamTable {
 public:
  struct Field {
    ParamInfo info{};
    std::function<double(const P&)> get{};                    // kReal, kInteger, kFlag, kChoice.
    std::function<void(P&, double)> set{};                    // Those; the value is already checked.
    std::function<std::string(const P&)> get_text{};          // kText only.
    std::function<void(P&, std::string)> set_text{};          // kText only.
    std::function<std::vector<double>(const P&)> get_list{};  // kRealList only.
    std::function<void(P&, std::vector<double>)> set_list{};  // kRealList only; already checked.
  };
  using Rule = std::function<absl::Status(const P&)>;

  // A direct member of P (`&P::member`), numeric or bool or enum.
  template <auto Member>
  ParamTable& Real(std::string name, double min_value, double max_value, std::string unit, std::string help) {
    return Add(Numeric<Member>({.name = std::move(name),
                                .type = ParamType::kReal,
                                .min_value = min_value,
                                .max_value = max_value,
                                .unit = std::move(unit),
                                .help = std::move(help)}));
  }
  template <auto Member>
  ParamTable& Integer(std::string name, double min_value, double max_value, std::string unit, std::string help) {
    return Add(Numeric<Member>({.name = std::move(name),
                                .type = ParamType::kInteger,
                                .min_value = min_value,
                                .max_value = max_value,
                                .unit = std::move(unit),
                                .help = std::move(help)}));
  }
  template <auto Member>
  ParamTable& Flag(std::string name, std::string help) {
    return Add(
        Numeric<Member>({.name = std::move(name), .type = ParamType::kFlag, .max_value = 1, .help = std::move(help)}));
  }
  template <auto Member>
  ParamTable& Choice(std::string name, std::vector<ParamChoice> choices, std::string help) {
    return Add(Numeric<Member>(
        {.name = std::move(name), .type = ParamType::kChoice, .help = std::move(help), .choices = std::move(choices)}));
  }
  template <auto Member>
  ParamTable& Text(std::string name, std::string help) {
    Field f;
    f.info = {.name = std::move(name), .type = ParamType::kText, .help = std::move(help)};
    f.get_text = [](const P& p) { return std::string(p.*Member); };
    f.set_text = [](P& p, std::string v) { p.*Member = std::move(v); };
    return Add(std::move(f));
  }
  // A `std::vector<double>` member: up to `max_count` values, each within [min_value, max_value]
  // (infinite bounds: any finite number).
  template <auto Member>
  ParamTable& RealList(std::string name, int max_count, double min_value, double max_value, std::string unit,
                       std::string help) {
    Field f;
    f.info = {.name = std::move(name),
              .type = ParamType::kRealList,
              .min_value = min_value,
              .max_value = max_value,
              .unit = std::move(unit),
              .help = std::move(help),
              .max_count = max_count};
    f.get_list = [](const P& p) { return p.*Member; };
    f.set_list = [](P& p, std::vector<double> v) { p.*Member = std::move(v); };
    return Add(std::move(f));
  }
  // Accepts `value` for the field added last, besides its range, meaning `meaning` (e.g. 0,
  // "chosen from the noise").
  ParamTable& Or(double value, std::string meaning) {
    fields_.back().info.special.push_back({value, std::move(meaning)});
    return *this;
  }
  // A numeric value reached through accessors (a nested member, or a value stored in another
  // form, such as a shading enum shown as a flag).
  ParamTable& Custom(ParamInfo info, std::function<double(const P&)> get, std::function<void(P&, double)> set) {
    return Add({.info = std::move(info), .get = std::move(get), .set = std::move(set)});
  }
  // Every field and rule of `inner`, reached through `member`, except the names in `skip`.
  template <class Inner>
  ParamTable& Include(Inner P::*member, const ParamTable<Inner>& inner, std::vector<std::string> skip = {}) {
    for (const auto& f : inner.fields()) {
      if (std::find(skip.begin(), skip.end(), f.info.name) != skip.end()) continue;
      Field g;
      g.info = f.info;
      if (f.get) g.get = [member, get = f.get](const P& p) { return get(p.*member); };
      if (f.set) g.set = [member, set = f.set](P& p, double v) { set(p.*member, v); };
      if (f.get_text) g.get_text = [member, get = f.get_text](const P& p) { return get(p.*member); };
      if (f.set_text) g.set_text = [member, set = f.set_text](P& p, std::string v) { set(p.*member, std::move(v)); };
      if (f.get_list) g.get_list = [member, get = f.get_list](const P& p) { return get(p.*member); };
      if (f.set_list) {
        g.set_list = [member, set = f.set_list](P& p, std::vector<double> v) { set(p.*member, std::move(v)); };
      }
      Add(std::move(g));
    }
    for (const auto& rule : inner.rules()) {
      rules_.push_back([member, rule](const P& p) { return rule(p.*member); });
    }
    return *this;
  }
  // A check across fields (e.g. marker_gap > marker_spacing), run after the per-field checks.
  ParamTable& AddRule(Rule rule) {
    rules_.push_back(std::move(rule));
    return *this;
  }

  const std::vector<Field>& fields() const { return fields_; }
  const std::vector<Rule>& rules() const { return rules_; }
  const Field* Find(std::string_view name) const {
    for (const auto& f : fields_) {
      if (f.info.name == name) return &f;
    }
    return nullptr;
  }

  // The descriptions, with the defaults of a default-constructed P.
  std::vector<ParamInfo> Describe() const {
    const P defaults{};
    std::vector<ParamInfo> out;
    for (const auto& f : fields_) {
      ParamInfo info = f.info;
      if (f.get) info.default_value = f.get(defaults);
      if (f.get_text) info.default_text = f.get_text(defaults);
      if (f.get_list) info.default_list = f.get_list(defaults);
      out.push_back(std::move(info));
    }
    return out;
  }

  // Every field in range, then every rule. Errors: kInvalidArgument naming the field and range.
  absl::Status Validate(const P& p) const {
    for (const auto& f : fields_) {
      if (f.get) LSQSURF_RETURN_IF_ERROR(CheckValue(f.info, f.get(p)));
      if (f.get_list) LSQSURF_RETURN_IF_ERROR(CheckList(f.info, f.get_list(p)));
    }
    for (const auto& rule : rules_) {
      if (absl::Status s = rule(p); !s.ok()) return s;
    }
    return absl::OkStatus();
  }

 private:
  template <class M>
  struct MemberOf;
  template <class C, class T>
  struct MemberOf<T C::*> {
    using Type = T;
  };

  template <auto Member>
  static Field Numeric(ParamInfo info) {
    using T = typename MemberOf<decltype(Member)>::Type;
    Field f;
    f.info = std::move(info);
    f.get = [](const P& p) -> double {
      if constexpr (std::is_enum_v<T>) {
        return static_cast<double>(static_cast<std::underlying_type_t<T>>(p.*Member));
      } else {
        return static_cast<double>(p.*Member);
      }
    };
    f.set = [](P& p, double v) {
      if constexpr (std::is_enum_v<T>) {
        p.*Member = static_cast<T>(static_cast<std::underlying_type_t<T>>(v));
      } else if constexpr (std::is_same_v<T, bool>) {
        p.*Member = v != 0;
      } else {
        p.*Member = static_cast<T>(v);
      }
    };
    return f;
  }

  ParamTable& Add(Field f) {
    fields_.push_back(std::move(f));
    return *this;
  }

  std::vector<Field> fields_;
  std::vector<Rule> rules_;
};

// A parameter struct of any type together with its table: how the job layer carries one job's
// parameters without knowing every engine. Copies are deep. Not thread-safe for writes.
class ParamSet {
 public:
  // The longest value a text parameter takes (a CSG expression is the longest in use).
  static constexpr size_t kMaxTextBytes = 64 << 10;
  ParamSet() = default;
  // `table` must outlive the set (tables are static).
  template <class P>
  explicit ParamSet(const ParamTable<P>& table, P value = P{})
      : holder_(std::make_unique<Holder<P>>(table, std::move(value))) {}
  ParamSet(const ParamSet& other) : holder_(other.holder_ ? other.holder_->Clone() : nullptr) {}
  ParamSet& operator=(const ParamSet& other) {
    holder_ = other.holder_ ? other.holder_->Clone() : nullptr;
    return *this;
  }
  ParamSet(ParamSet&&) noexcept = default;
  ParamSet& operator=(ParamSet&&) noexcept = default;

  bool empty() const { return holder_ == nullptr; }
  // Whether both hold the same struct type.
  bool SameType(const ParamSet& other) const {
    return holder_ != nullptr && other.holder_ != nullptr && holder_->type() == other.holder_->type();
  }
  std::vector<ParamInfo> Describe() const;
  // The named field's description, or nullptr.
  const ParamInfo* Info(std::string_view name) const;

  // Sets one value, checked against its description. Errors: kInvalidArgument for an unknown
  // name (listing the valid ones), a value out of range, a text value for a number.
  absl::Status Set(std::string_view name, double value);
  absl::Status SetText(std::string_view name, std::string value);
  absl::Status SetList(std::string_view name, std::vector<double> values);
  // Parses `text` as the parameter's type: a number, true/false/0/1, a choice's name, or numbers
  // separated by commas.
  absl::Status Parse(std::string_view name, std::string_view text);
  // The current value (choices by value); nullopt for an unknown name or a text field.
  std::optional<double> Get(std::string_view name) const;
  std::optional<std::string> GetText(std::string_view name) const;
  std::optional<std::vector<double>> GetList(std::string_view name) const;

  // Ranges of every field, then the cross-field rules.
  absl::Status Validate() const;

  // "name=value;..." of every field (text values escaped): what the job store keeps.
  std::string Encode() const;
  // Applies an Encode() string. Names the table no longer has are skipped (stored jobs outlive
  // removed parameters). Errors: kInvalidArgument (a value that no longer fits).
  absl::Status Decode(std::string_view text);

  // The struct, or nullptr when the set holds another type.
  template <class P>
  const P* As() const {
    if (holder_ == nullptr || holder_->type() != typeid(P)) return nullptr;
    return &static_cast<const Holder<P>*>(holder_.get())->value;
  }
  // The struct for direct edits, which skip the per-field checks (Validate() before use).
  template <class P>
  P* Mutable() {
    if (holder_ == nullptr || holder_->type() != typeid(P)) return nullptr;
    return &static_cast<Holder<P>*>(holder_.get())->value;
  }

 private:
  struct HolderBase {
    virtual ~HolderBase() = default;
    virtual std::unique_ptr<HolderBase> Clone() const = 0;
    virtual const std::type_info& type() const = 0;
    virtual std::vector<ParamInfo> Describe() const = 0;
    virtual const ParamInfo* Info(std::string_view name) const = 0;
    virtual void SetNumber(std::string_view name, double value) = 0;
    virtual void SetText(std::string_view name, std::string value) = 0;
    virtual void SetList(std::string_view name, std::vector<double> values) = 0;
    virtual std::optional<double> GetNumber(std::string_view name) const = 0;
    virtual std::optional<std::string> GetText(std::string_view name) const = 0;
    virtual std::optional<std::vector<double>> GetList(std::string_view name) const = 0;
    virtual absl::Status Validate() const = 0;
  };
  template <class P>
  struct Holder final : HolderBase {
    Holder(const ParamTable<P>& t, P v) : table(t), value(std::move(v)) {}
    std::unique_ptr<HolderBase> Clone() const override { return std::make_unique<Holder>(table, value); }
    const std::type_info& type() const override { return typeid(P); }
    std::vector<ParamInfo> Describe() const override { return table.Describe(); }
    const ParamInfo* Info(std::string_view name) const override {
      const auto* f = table.Find(name);
      return f ? &f->info : nullptr;
    }
    void SetNumber(std::string_view name, double v) override {
      if (const auto* f = table.Find(name); f && f->set) f->set(value, v);
    }
    void SetText(std::string_view name, std::string v) override {
      if (const auto* f = table.Find(name); f && f->set_text) f->set_text(value, std::move(v));
    }
    void SetList(std::string_view name, std::vector<double> v) override {
      if (const auto* f = table.Find(name); f && f->set_list) f->set_list(value, std::move(v));
    }
    std::optional<double> GetNumber(std::string_view name) const override {
      const auto* f = table.Find(name);
      if (f == nullptr || !f->get) return std::nullopt;
      return f->get(value);
    }
    std::optional<std::string> GetText(std::string_view name) const override {
      const auto* f = table.Find(name);
      if (f == nullptr || !f->get_text) return std::nullopt;
      return f->get_text(value);
    }
    std::optional<std::vector<double>> GetList(std::string_view name) const override {
      const auto* f = table.Find(name);
      if (f == nullptr || !f->get_list) return std::nullopt;
      return f->get_list(value);
    }
    absl::Status Validate() const override { return table.Validate(value); }
    const ParamTable<P>& table;
    P value;
  };

  absl::Status UnknownName(std::string_view name) const;
  std::unique_ptr<HolderBase> holder_;
};

// A Markdown table of the parameters (name, type, default, range, unit, meaning): the
// generated parameter reference.
std::string ParamReferenceMarkdown(const std::vector<ParamInfo>& params);

}  // namespace lsqsurf::core
