// worker/core/status.h — error propagation between modules.
//
// Modules return `absl::Status` / `absl::StatusOr<T>`; the 2022 abseil shipped with Debian lacks
// the return-if-error helpers, so these macros stand in for them.
#pragma once

#include <exception>
#include <new>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace lsqsurf::core {

// `status` with "`context`: " before its message, and its code kept.
inline absl::Status WithContext(std::string_view context, const absl::Status& status) {
  return absl::Status(status.code(), std::string(context) + ": " + std::string(status.message()));
}

// What `run` returns (an absl::Status or StatusOr), or what it throws as a status: out of memory
// as kResourceExhausted ("the `subject` ran out of memory"), anything else as kInternal. So that
// an engine that throws fails its own job and never the server.
template <typename Run>
auto CatchEngineErrors(std::string_view subject, Run&& run) -> decltype(run()) {
  try {
    return run();
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("the " + std::string(subject) + " ran out of memory");
  } catch (const std::exception& e) {
    return absl::InternalError("engine error: " + std::string(e.what()));
  }
}

}  // namespace lsqsurf::core

#define LSQSURF_STATUS_CONCAT_INNER(a, b) a##b
#define LSQSURF_STATUS_CONCAT(a, b) LSQSURF_STATUS_CONCAT_INNER(a, b)

// Returns from the enclosing function when `expr` (an absl::Status) is not OK. The variable's
// name is unique per line, so the macro nests (e.g. inside a lambda passed to another use).
#define LSQSURF_RETURN_IF_ERROR(expr)                                           \
  do {                                                                          \
    if (absl::Status LSQSURF_STATUS_CONCAT(lsqsurf_status_, __LINE__) = (expr); \
        !LSQSURF_STATUS_CONCAT(lsqsurf_status_, __LINE__).ok())                 \
      return LSQSURF_STATUS_CONCAT(lsqsurf_status_, __LINE__);                  \
  } while (false)

// `LSQSURF_ASSIGN_OR_RETURN(auto x, MakeX());` declares `x` from an absl::StatusOr, or returns
// its status from the enclosing function.
#define LSQSURF_ASSIGN_OR_RETURN(lhs, expr) \
  LSQSURF_ASSIGN_OR_RETURN_IMPL(LSQSURF_STATUS_CONCAT(lsqsurf_statusor_, __LINE__), lhs, expr)
#define LSQSURF_ASSIGN_OR_RETURN_IMPL(statusor, lhs, expr) \
  auto statusor = (expr);                                  \
  if (!statusor.ok()) return statusor.status();            \
  lhs = *std::move(statusor)
