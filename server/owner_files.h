// server/owner_files.h — the server's own small files that hold secrets or name who may use it
// (the token file, the staged certificate and key): read whole, written readable by the owner only.
#pragma once

#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace lsqsurf::server {

// The file's bytes; `what` names it in the error ("token file"). Errors: kNotFound.
absl::StatusOr<std::string> ReadOwnerFile(const std::string& path, std::string_view what);

// Replaces the file in one step (a reader sees the old bytes or the new ones), mode 0600.
// Errors: kUnavailable naming `what` and the reason.
absl::Status WriteOwnerFile(const std::string& path, std::string_view text, std::string_view what);

}  // namespace lsqsurf::server
