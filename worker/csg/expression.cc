#include "worker/csg/expression.h"

#include <cctype>
#include <charconv>
#include <cmath>
#include <optional>

#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::csg {
namespace {

// An argument a call accepts: how many numbers, and the default when it may be left out.
struct ArgSpec {
  const char* key;
  int count;  // 1 or 3 (a size takes 1 or 3).
  std::optional<std::vector<double>> by_default;
  bool positive = false;  // Every number > 0.
};

struct CallSpec {
  const char* name;
  NodeKind kind;
  int min_children, max_children;
  std::vector<ArgSpec> args;
};

ArgSpec Required(const char* key, int count, bool positive = false) { return {key, count, std::nullopt, positive}; }
ArgSpec Optional(const char* key, std::vector<double> by_default, bool positive = false) {
  return {key, static_cast<int>(by_default.size() == 1 ? 1 : 3), std::move(by_default), positive};
}
ArgSpec Point(const char* key) { return Optional(key, {0, 0, 0}); }

const std::vector<CallSpec>& Calls() {
  // Box arguments have no defaults of their own: Finish() checks their combinations.
  static const auto* calls = new std::vector<CallSpec>{
      {"union", NodeKind::kUnion, 2, kMaxNodes, {}},
      {"intersection", NodeKind::kIntersection, 2, kMaxNodes, {}},
      {"difference", NodeKind::kDifference, 2, kMaxNodes, {}},
      {"sphere", NodeKind::kSphere, 0, 0, {Point("c"), Required("r", 1, true)}},
      {"box",
       NodeKind::kBox,
       0,
       0,
       {Required("min", 3), Required("max", 3), Required("c", 3), Required("size", 3, true)}},
      {"cylinder", NodeKind::kCylinder, 0, 0, {Required("a", 3), Required("b", 3), Required("r", 1, true)}},
      {"torus",
       NodeKind::kTorus,
       0,
       0,
       {Point("c"), Optional("axis", {0, 0, 1}), Required("R", 1, true), Required("r", 1, true)}},
      {"plane", NodeKind::kPlane, 0, 0, {Point("p"), Required("n", 3)}},
      {"translate", NodeKind::kTranslate, 1, 1, {Required("t", 3)}},
      {"rotate", NodeKind::kRotate, 1, 1, {Required("axis", 3), Required("deg", 1), Point("c")}},
      {"scale", NodeKind::kScale, 1, 1, {Required("s", 1, true), Point("c")}},
  };
  return *calls;
}

bool IsNameChar(char c) { return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '_'; }
bool IsIdChar(char c) { return IsNameChar(c) || c == '-'; }
bool StartsNumber(char c) {
  return std::isdigit(static_cast<unsigned char>(c)) != 0 || c == '-' || c == '+' || c == '.';
}

class Parser {
 public:
  explicit Parser(std::string_view text) : text_(text) {}

  absl::StatusOr<CsgNode> Parse() {
    auto root = Operand(0);
    if (!root.ok()) return root.status();
    SkipBlanks();
    if (pos_ < text_.size()) return Error("unexpected text after the expression");
    return root;
  }

 private:
  absl::Status Error(std::string_view what) const {
    return absl::InvalidArgumentError(core::StrCat("csg expression, column ", pos_ + 1, ": ", what));
  }
  void SkipBlanks() {
    while (pos_ < text_.size() && std::isspace(static_cast<unsigned char>(text_[pos_])) != 0) ++pos_;
  }
  void SkipSeparators() {
    while (pos_ < text_.size() && (text_[pos_] == ',' || std::isspace(static_cast<unsigned char>(text_[pos_])) != 0))
      ++pos_;
  }
  std::string_view Word(bool (*accept)(char)) {
    const size_t start = pos_;
    while (pos_ < text_.size() && accept(text_[pos_])) ++pos_;
    return text_.substr(start, pos_ - start);
  }

  absl::StatusOr<double> NumberAt() {
    const char* begin = text_.data() + pos_;
    const char* end = text_.data() + text_.size();
    if (begin < end && *begin == '+') ++begin;
    double value = 0;
    auto [p, ec] = std::from_chars(begin, end, value);
    if (ec != std::errc() || !std::isfinite(value)) return Error("expected a finite number");
    pos_ = static_cast<size_t>(p - text_.data());
    return value;
  }

  absl::StatusOr<CsgNode> Operand(int nesting) {
    if (nesting > kMaxNesting) return Error(core::StrCat("nested deeper than ", kMaxNesting, " levels"));
    if (++nodes_ > kMaxNodes) return Error(core::StrCat("more than ", kMaxNodes, " operations and primitives"));
    SkipBlanks();
    const size_t start = pos_;
    const std::string name(Word(IsNameChar));
    if (name.empty()) return Error("expected an operation, a primitive or job:ID");
    SkipBlanks();
    if (name == "job" && pos_ < text_.size() && text_[pos_] == ':') {
      ++pos_;
      SkipBlanks();
      CsgNode node;
      node.kind = NodeKind::kJob;
      node.job_id = std::string(Word(IsIdChar));
      if (node.job_id.empty()) return Error("expected a job id after 'job:'");
      return node;
    }
    const CallSpec* spec = nullptr;
    for (const CallSpec& c : Calls()) {
      if (name == c.name) spec = &c;
    }
    if (spec == nullptr) {
      pos_ = start;
      return Error(core::StrCat("unknown name '", name,
                                "'; expected union, intersection, difference, sphere, box, cylinder, torus, plane, "
                                "translate, rotate, scale or job:ID"));
    }
    if (pos_ >= text_.size() || text_[pos_] != '(') return Error(core::StrCat("expected '(' after ", name));
    ++pos_;
    CsgNode node;
    node.kind = spec->kind;
    for (;;) {
      SkipSeparators();
      if (pos_ >= text_.size()) return Error(core::StrCat("missing ')' of ", name));
      if (text_[pos_] == ')') {
        ++pos_;
        break;
      }
      // A named argument is a name followed by '='; anything else is an operand.
      const size_t item = pos_;
      const std::string key(Word(IsNameChar));
      SkipBlanks();
      if (!key.empty() && pos_ < text_.size() && text_[pos_] == '=') {
        ++pos_;
        LSQSURF_RETURN_IF_ERROR(Argument(*spec, key, node));
        continue;
      }
      pos_ = item;
      auto child = Operand(nesting + 1);
      if (!child.ok()) return child.status();
      node.children.push_back(*std::move(child));
    }
    return Finish(*spec, std::move(node), start);
  }

  absl::Status Argument(const CallSpec& spec, const std::string& key, CsgNode& node) {
    const ArgSpec* arg = nullptr;
    for (const ArgSpec& a : spec.args) {
      if (key == a.key) arg = &a;
    }
    if (arg == nullptr) {
      std::string known;
      for (const ArgSpec& a : spec.args) core::StrAppend(&known, known.empty() ? "" : ", ", a.key);
      return Error(
          core::StrCat(spec.name, " has no argument '", key, "'",
                       known.empty() ? std::string("; it takes operands only") : core::StrCat("; it takes ", known)));
    }
    if (node.args.contains(key)) return Error(core::StrCat("'", key, "' given twice"));
    std::vector<double> values;
    for (;;) {
      SkipBlanks();
      auto v = NumberAt();
      if (!v.ok()) return v.status();
      values.push_back(*v);
      // More numbers follow a comma only when a number comes next (else the comma separates).
      size_t look = pos_;
      while (look < text_.size() && std::isspace(static_cast<unsigned char>(text_[look])) != 0) ++look;
      if (look >= text_.size() || text_[look] != ',') break;
      ++look;
      while (look < text_.size() && std::isspace(static_cast<unsigned char>(text_[look])) != 0) ++look;
      if (look >= text_.size() || !StartsNumber(text_[look])) break;
      pos_ = look;
    }
    const bool size_of_cube = spec.kind == NodeKind::kBox && key == "size" && values.size() == 1;
    if (size_of_cube) values.assign(3, values[0]);
    if (static_cast<int>(values.size()) != arg->count) {
      return Error(core::StrCat(spec.name, " ", key, " takes ", arg->count == 1 ? "one number" : "three numbers x,y,z",
                                ", not ", values.size()));
    }
    if (arg->positive) {
      for (double v : values) {
        if (!(v > 0)) return Error(core::StrCat(spec.name, " ", key, " must be positive"));
      }
    }
    node.args[key] = std::move(values);
    return absl::OkStatus();
  }

  absl::StatusOr<CsgNode> Finish(const CallSpec& spec, CsgNode node, size_t start) {
    const auto at = [&](std::string_view what) {
      return absl::InvalidArgumentError(core::StrCat("csg expression, column ", start + 1, ": ", spec.name, " ", what));
    };
    const int children = static_cast<int>(node.children.size());
    if (children < spec.min_children || children > spec.max_children) {
      if (spec.max_children == 0) return at("takes no operands");
      if (spec.min_children == spec.max_children) return at("takes exactly one operand");
      return at(core::StrCat("needs at least ", spec.min_children, " operands"));
    }
    if (spec.kind == NodeKind::kBox) {
      const bool corners = node.args.contains("min") || node.args.contains("max");
      const bool centred = node.args.contains("c") || node.args.contains("size");
      if (corners == centred) return at("needs either min= and max= or size= (with c=, default the origin)");
      if (corners) {
        if (!node.args.contains("min") || !node.args.contains("max")) return at("needs both min= and max=");
        for (int a = 0; a < 3; ++a) {
          if (!(node.args["min"][static_cast<size_t>(a)] < node.args["max"][static_cast<size_t>(a)]))
            return at("min must be below max on every axis");
        }
      } else {
        if (!node.args.contains("size")) return at("needs size=");
        if (!node.args.contains("c")) node.args["c"] = {0, 0, 0};
        const core::Vec3d c = node.Vector("c"), half = node.Vector("size") / 2;
        const core::Vec3d lo = c - half, hi = c + half;
        node.args.erase("c");
        node.args.erase("size");
        node.args["min"] = {lo.x(), lo.y(), lo.z()};
        node.args["max"] = {hi.x(), hi.y(), hi.z()};
      }
      return node;
    }
    for (const ArgSpec& a : spec.args) {
      if (node.args.contains(a.key)) continue;
      if (!a.by_default) return at(core::StrCat("needs ", a.key, "="));
      node.args[a.key] = *a.by_default;
    }
    const auto nonzero = [&](const char* key) { return node.Vector(key).norm() > 0; };
    if (spec.kind == NodeKind::kCylinder && !((node.Vector("b") - node.Vector("a")).norm() > 0))
      return at("needs a and b apart");
    if ((spec.kind == NodeKind::kTorus || spec.kind == NodeKind::kRotate) && !nonzero("axis"))
      return at("needs a non-zero axis");
    if (spec.kind == NodeKind::kPlane && !nonzero("n")) return at("needs a non-zero normal n");
    return node;
  }

  std::string_view text_;
  size_t pos_ = 0;
  int nodes_ = 0;
};

void CollectJobs(const CsgNode& node, std::vector<std::string>& out) {
  if (node.kind == NodeKind::kJob) {
    for (const auto& id : out) {
      if (id == node.job_id) return;
    }
    out.push_back(node.job_id);
  }
  for (const CsgNode& c : node.children) CollectJobs(c, out);
}

}  // namespace

core::Vec3d CsgNode::Vector(const std::string& key) const {
  const std::vector<double>& v = args.at(key);
  return {v[0], v[1], v[2]};
}

double CsgNode::Number(const std::string& key) const { return args.at(key)[0]; }

absl::StatusOr<CsgNode> ParseCsg(std::string_view text) {
  if (text.size() > kMaxExpressionBytes) {
    return absl::InvalidArgumentError(
        core::StrCat("the csg expression has ", text.size(), " bytes; at most ", kMaxExpressionBytes, " are accepted"));
  }
  auto root = Parser(text).Parse();
  if (!root.ok()) return root;
  if (ReferencedJobs(*root).size() > static_cast<size_t>(kMaxJobReferences)) {
    return absl::InvalidArgumentError(
        core::StrCat("the csg expression refers to more than ", kMaxJobReferences, " jobs"));
  }
  return root;
}

std::vector<std::string> ReferencedJobs(const CsgNode& root) {
  std::vector<std::string> out;
  CollectJobs(root, out);
  return out;
}

}  // namespace lsqsurf::csg
