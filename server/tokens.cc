#include "server/tokens.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/rand.h>
#include <unistd.h>

#include <cctype>
#include <cstring>
#include <sstream>
#include <stdexcept>

#include "server/owner_files.h"
#include "worker/core/strings.h"

namespace lsqsurf::server {
namespace {

using core::StrCat;

constexpr size_t kSaltBytes = 16;
constexpr size_t kTokenBytes = 32;
constexpr char kTokenPrefix[] = "lsq_";
constexpr char kFileHeader[] =
    "# lsqsurfd tokens: name role salt sha256(salt || token) [max_jobs=N] [max_stored_mib=N] [max_upload_mib=N]\n"
    "# Edit with `lsqsurfd tokens add|list|revoke`; lsqsurfd reads this file again on SIGHUP.\n";

std::string Hex(const unsigned char* bytes, size_t n) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string out(2 * n, '0');
  for (size_t i = 0; i < n; ++i) {
    out[2 * i] = kDigits[bytes[i] >> 4];
    out[2 * i + 1] = kDigits[bytes[i] & 15];
  }
  return out;
}

bool FromHex(std::string_view hex, std::string* out) {
  if (hex.size() % 2 != 0) return false;
  out->clear();
  for (size_t i = 0; i < hex.size(); i += 2) {
    int value = 0;
    for (char c : hex.substr(i, 2)) {
      const int digit = c >= '0' && c <= '9' ? c - '0' : c >= 'a' && c <= 'f' ? c - 'a' + 10 : -1;
      if (digit < 0) return false;
      value = value * 16 + digit;
    }
    out->push_back(static_cast<char>(value));
  }
  return true;
}

std::string Sha256(std::string_view salt, std::string_view token) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_MD_CTX* ctx = EVP_MD_CTX_new();
  const bool ok = ctx != nullptr && EVP_DigestInit_ex(ctx, EVP_sha256(), nullptr) == 1 &&
                  EVP_DigestUpdate(ctx, salt.data(), salt.size()) == 1 &&
                  EVP_DigestUpdate(ctx, token.data(), token.size()) == 1 &&
                  EVP_DigestFinal_ex(ctx, digest, &length) == 1;
  EVP_MD_CTX_free(ctx);
  if (!ok) throw std::runtime_error("SHA-256 is not available");
  return std::string(reinterpret_cast<const char*>(digest), length);
}

bool ValidName(std::string_view name) {
  if (name.empty() || name.size() > 64) return false;
  for (char c : name) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && std::strchr("_.@-", c) == nullptr) return false;
  }
  return true;
}

// "key=N" into the entry's quota; false for an unknown key or a bad number.
bool SetQuota(std::string_view field, TokenEntry& entry) {
  const size_t eq = field.find('=');
  if (eq == std::string_view::npos) return false;
  const std::string key(field.substr(0, eq)), text(field.substr(eq + 1));
  char* end = nullptr;
  const long long value = std::strtoll(text.c_str(), &end, 10);
  if (text.empty() || *end != '\0' || value < 0 || value > (int64_t{1} << 40)) return false;
  if (key == "max_jobs" && value <= 1'000'000) {
    entry.max_jobs = static_cast<int>(value);
  } else if (key == "max_stored_mib") {
    entry.max_stored_mib = value;
  } else if (key == "max_upload_mib") {
    entry.max_upload_mib = value;
  } else {
    return false;
  }
  return true;
}

std::string FormatEntry(const TokenEntry& e) {
  std::string line = StrCat(e.name, " ", RoleName(e.role), " ", e.salt_hex, " ", e.hash_hex);
  if (e.max_jobs > 0) core::StrAppend(&line, " max_jobs=", e.max_jobs);
  if (e.max_stored_mib > 0) core::StrAppend(&line, " max_stored_mib=", e.max_stored_mib);
  if (e.max_upload_mib > 0) core::StrAppend(&line, " max_upload_mib=", e.max_upload_mib);
  return line + "\n";
}

}  // namespace

const char* RoleName(Role role) { return role == Role::kAdmin ? "admin" : "user"; }

absl::StatusOr<Role> ParseRole(std::string_view text) {
  if (text == "user") return Role::kUser;
  if (text == "admin") return Role::kAdmin;
  return absl::InvalidArgumentError(StrCat("unknown role '", text, "'; roles are user and admin"));
}

absl::StatusOr<std::vector<TokenEntry>> ParseTokens(std::string_view text, std::string_view source) {
  std::vector<TokenEntry> entries;
  std::istringstream lines{std::string(text)};
  int number = 0;
  for (std::string line; std::getline(lines, line);) {
    ++number;
    std::istringstream fields(line);
    std::vector<std::string> f;
    for (std::string field; fields >> field;) f.push_back(field);
    if (f.empty() || f[0][0] == '#') continue;
    const auto bad = [&](std::string_view why) {
      return absl::InvalidArgumentError(StrCat(source, ":", number, ": ", why));
    };
    if (f.size() < 4) return bad("expected: name role salt hash [max_jobs=N] [max_stored_mib=N] [max_upload_mib=N]");
    TokenEntry e;
    e.name = f[0];
    if (!ValidName(e.name)) return bad("a name is 1 to 64 letters, digits or _.@-");
    auto role = ParseRole(f[1]);
    if (!role.ok()) return bad(std::string(role.status().message()));
    e.role = *role;
    std::string bytes;
    if (!FromHex(f[2], &bytes) || bytes.size() != kSaltBytes) return bad("the salt must be 32 hex digits");
    if (!FromHex(f[3], &bytes) || bytes.size() != 32) return bad("the hash must be 64 hex digits");
    e.salt_hex = f[2];
    e.hash_hex = f[3];
    for (size_t i = 4; i < f.size(); ++i) {
      if (!SetQuota(f[i], e)) return bad(StrCat("unknown quota '", f[i], "'"));
    }
    for (const auto& other : entries) {
      if (other.name == e.name) return bad(StrCat("the name '", e.name, "' is taken by an earlier line"));
    }
    entries.push_back(std::move(e));
  }
  return entries;
}

absl::StatusOr<std::vector<TokenEntry>> ReadTokenFile(const std::string& path) {
  auto text = ReadOwnerFile(path, "token file");
  if (!text.ok()) return text.status();
  return ParseTokens(*text, path);
}

absl::StatusOr<std::string> AddToken(const std::string& path, TokenEntry entry) {
  if (!ValidName(entry.name)) {
    return absl::InvalidArgumentError(StrCat("'", entry.name, "': a name is 1 to 64 letters, digits or _.@-"));
  }
  std::string text = kFileHeader;
  if (::access(path.c_str(), F_OK) == 0) {
    auto existing = ReadOwnerFile(path, "token file");
    if (!existing.ok()) return existing.status();
    auto entries = ParseTokens(*existing, path);
    if (!entries.ok()) return entries.status();
    for (const auto& e : *entries) {
      if (e.name == entry.name) return absl::AlreadyExistsError(StrCat("the name '", entry.name, "' has a token"));
    }
    text = *std::move(existing);
    if (!text.empty() && text.back() != '\n') text += '\n';
  }
  unsigned char random[kSaltBytes + kTokenBytes];
  if (RAND_bytes(random, sizeof(random)) != 1) return absl::UnavailableError("no random bytes for a token");
  const std::string token = kTokenPrefix + Hex(random + kSaltBytes, kTokenBytes);
  const std::string salt(reinterpret_cast<const char*>(random), kSaltBytes);
  const std::string digest = Sha256(salt, token);
  entry.salt_hex = Hex(random, kSaltBytes);
  entry.hash_hex = Hex(reinterpret_cast<const unsigned char*>(digest.data()), digest.size());
  text += FormatEntry(entry);
  if (absl::Status s = WriteOwnerFile(path, text, "token file"); !s.ok()) return s;
  return token;
}

absl::Status RevokeToken(const std::string& path, const std::string& name) {
  auto text = ReadOwnerFile(path, "token file");
  if (!text.ok()) return text.status();
  auto entries = ParseTokens(*text, path);
  if (!entries.ok()) return entries.status();
  // Lines are kept as they are (comments included) but the named one.
  std::istringstream lines(*text);
  std::string kept;
  bool found = false;
  for (std::string line; std::getline(lines, line);) {
    std::istringstream fields(line);
    std::string first;
    fields >> first;
    if (first == name) {
      found = true;
      continue;
    }
    kept += line + "\n";
  }
  if (!found) return absl::NotFoundError(StrCat("no token named '", name, "' in ", path));
  return WriteOwnerFile(path, kept, "token file");
}

absl::StatusOr<std::unique_ptr<TokenTable>> TokenTable::Load(const std::string& path) {
  std::unique_ptr<TokenTable> table(new TokenTable(path));
  if (auto loaded = table->Reload(); !loaded.ok()) return loaded.status();
  return table;
}

absl::StatusOr<size_t> TokenTable::Reload() {
  auto entries = ReadTokenFile(path_);
  if (!entries.ok()) return entries.status();
  const size_t count = entries->size();
  auto table = std::make_shared<const std::vector<TokenEntry>>(*std::move(entries));
  std::lock_guard lock(mutex_);
  entries_ = std::move(table);
  return count;
}

absl::StatusOr<Caller> TokenTable::Authenticate(std::string_view authorization) const {
  constexpr std::string_view kScheme = "Bearer ";
  if (authorization.empty()) {
    return absl::UnauthenticatedError(
        "this server needs a token: set LSQSURF_TOKEN or give --token-file (the header is authorization: Bearer "
        "TOKEN)");
  }
  if (authorization.substr(0, kScheme.size()) != kScheme) {
    return absl::UnauthenticatedError("the authorization header must be 'Bearer TOKEN'");
  }
  const std::string_view token = authorization.substr(kScheme.size());
  std::shared_ptr<const std::vector<TokenEntry>> entries;
  {
    std::lock_guard lock(mutex_);
    entries = entries_;
  }
  std::string salt, expected;
  for (const TokenEntry& e : *entries) {
    FromHex(e.salt_hex, &salt);
    FromHex(e.hash_hex, &expected);
    const std::string digest = Sha256(salt, token);
    if (CRYPTO_memcmp(digest.data(), expected.data(), digest.size()) != 0) continue;
    Caller caller;
    caller.name = e.name;
    caller.submitter.sees_all = e.role == Role::kAdmin;
    caller.submitter.owner = e.name;
    caller.submitter.max_active_jobs = e.max_jobs;
    caller.submitter.max_stored_bytes = e.max_stored_mib << 20;
    caller.submitter.max_upload_bytes = e.max_upload_mib << 20;
    return caller;
  }
  return absl::UnauthenticatedError("unknown token (revoked, or from another server)");
}

}  // namespace lsqsurf::server
