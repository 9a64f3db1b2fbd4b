// server/tokens.h — bearer tokens: the token file, and whom a call's token names.
//
// A token file holds one line per token: its holder's name, role, quotas, and the token as a
// salted SHA-256 (the token itself is shown once, when made, and kept nowhere):
//
//   # name role salt sha256(salt || token) [max_jobs=N] [max_stored_mib=N] [max_upload_mib=N]
//   alice user 8c1f...(32 hex) 5be0...(64 hex) max_jobs=4 max_stored_mib=2048
//
// Tokens are 32 random bytes, so a fast salted hash is enough: there is no password to guess.
// `lsqsurfd tokens add|list|revoke` edit the file (AddToken, RevokeToken); lsqsurfd reads it
// at start and again on SIGHUP (TokenTable::Reload).
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/jobs/job_service.h"

namespace lsqsurf::server {

enum class Role { kUser, kAdmin };

// One line of a token file.
struct TokenEntry {
  std::string name;  // Its holder: 1..64 of [A-Za-z0-9_.@-]; shown in logs, recorded as jobs' owner.
  Role role = Role::kUser;
  std::string salt_hex;  // 16 random bytes.
  std::string hash_hex;  // SHA-256 of the salt's bytes followed by the token's text.
  // Quotas, 0 = none: jobs queued or running, bytes kept by the holder's jobs, one upload.
  int max_jobs = 0;
  int64_t max_stored_mib = 0;
  int64_t max_upload_mib = 0;
};

const char* RoleName(Role role);
// "user" or "admin". Errors: kInvalidArgument.
absl::StatusOr<Role> ParseRole(std::string_view text);

// The entries of a token file's text; `source` names it in errors. Errors: kInvalidArgument
// naming the line (bad field, duplicate name).
absl::StatusOr<std::vector<TokenEntry>> ParseTokens(std::string_view text, std::string_view source);
// Reads and parses a token file. Errors: kNotFound, kInvalidArgument.
absl::StatusOr<std::vector<TokenEntry>> ReadTokenFile(const std::string& path);

// Makes a token for `entry` (its name, role and quotas; salt and hash are filled in), adds it to
// the file (made, readable by its owner only, when missing) and returns the token, the only time
// it is seen. Errors: kInvalidArgument (bad name), kAlreadyExists (name taken), kUnavailable (I/O).
absl::StatusOr<std::string> AddToken(const std::string& path, TokenEntry entry);
// Removes the named token from the file. Errors: kNotFound, kUnavailable.
absl::Status RevokeToken(const std::string& path, const std::string& name);

// Who makes a call and what they may do.
struct Caller {
  std::string name;           // The token's name; empty when the server takes no tokens.
  jobs::Submitter submitter;  // Owner and quotas of the jobs they submit; sees_all for an admin.
  bool admin() const { return submitter.sees_all; }
};

// The tokens lsqsurfd accepts. Thread-safe: Authenticate may run while Reload replaces the table.
class TokenTable {
 public:
  // Errors: those of ReadTokenFile.
  static absl::StatusOr<std::unique_ptr<TokenTable>> Load(const std::string& path);
  // Reads the file again; on an error the tokens in use stay. Returns how many tokens there are.
  absl::StatusOr<size_t> Reload();
  // The caller an "authorization" header value ("Bearer TOKEN") names. Errors: kUnauthenticated
  // (missing, malformed or unknown token; the message never repeats the token).
  absl::StatusOr<Caller> Authenticate(std::string_view authorization) const;
  const std::string& path() const { return path_; }

 private:
  explicit TokenTable(std::string path) : path_(std::move(path)) {}
  std::string path_;
  mutable std::mutex mutex_;
  std::shared_ptr<const std::vector<TokenEntry>> entries_;  // Replaced whole by Reload.
};

}  // namespace lsqsurf::server
