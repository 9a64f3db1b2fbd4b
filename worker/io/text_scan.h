// worker/io/text_scan.h — line and number scanning shared by the text formats (internal).
#pragma once

#include <charconv>
#include <initializer_list>
#include <string>
#include <string_view>

namespace lsqsurf::io::internal {

// Iterates over the lines of a buffer, counting them from 1; tolerates \r\n endings.
class LineReader {
 public:
  explicit LineReader(std::string_view text) : text_(text) {}
  bool Next(std::string_view& line) {
    if (pos_ >= text_.size()) return false;
    size_t end = text_.find('\n', pos_);
    if (end == std::string_view::npos) end = text_.size();
    line = text_.substr(pos_, end - pos_);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    pos_ = end + 1;
    ++line_number_;
    return true;
  }
  size_t line_number() const { return line_number_; }
  size_t offset() const { return pos_; }

 private:
  std::string_view text_;
  size_t pos_ = 0;
  size_t line_number_ = 0;
};

// Splits off the next whitespace-separated token; empty when none is left.
inline std::string_view NextToken(std::string_view& s) {
  size_t b = 0;
  while (b < s.size() && (s[b] == ' ' || s[b] == '\t')) ++b;
  size_t e = b;
  while (e < s.size() && s[e] != ' ' && s[e] != '\t') ++e;
  std::string_view tok = s.substr(b, e - b);
  s.remove_prefix(e);
  return tok;
}

// Parses the whole token as a number; false on any trailing garbage.
template <class T>
bool ParseNumber(std::string_view tok, T& out) {
  if (!tok.empty() && tok.front() == '+') tok.remove_prefix(1);
  const auto [ptr, ec] = std::from_chars(tok.data(), tok.data() + tok.size(), out);
  return ec == std::errc() && ptr == tok.data() + tok.size() && !tok.empty();
}

// Appends the shortest decimal form that reads back to exactly `v`.
inline void AppendFloat(std::string& out, float v) {
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof(buf), v);
  out.append(buf, r.ptr);
}

// Appends the values separated by single spaces, then a newline.
inline void AppendFloats(std::string& out, std::initializer_list<float> values) {
  bool first = true;
  for (float v : values) {
    if (!first) out.push_back(' ');
    first = false;
    AppendFloat(out, v);
  }
  out.push_back('\n');
}

}  // namespace lsqsurf::io::internal
