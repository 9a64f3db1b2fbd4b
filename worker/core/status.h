// worker/core/status.h — error propagation between modules.
//
// Modules return `absl::Status` / `absl::StatusOr<T>`; the 2022 abseil shipped with Debian lacks
// the return-if-error helpers, so these two macros stand in for them.
#pragma once

#include "absl/status/status.h"
#include "absl/status/statusor.h"

#define LSQSURF_CONCAT_INNER_(a, b) a##b
#define LSQSURF_CONCAT_(a, b) LSQSURF_CONCAT_INNER_(a, b)

// Returns from the enclosing function when `expr` (an absl::Status) is not OK.
#define LSQSURF_RETURN_IF_ERROR(expr)                          \
  do {                                                         \
    if (absl::Status lsqsurf_status_ = (expr); !lsqsurf_status_.ok()) \
      return lsqsurf_status_;                                  \
  } while (false)

// `LSQSURF_ASSIGN_OR_RETURN(auto x, MakeX());` unwraps a StatusOr or returns its error.
#define LSQSURF_ASSIGN_OR_RETURN(lhs, expr) \
  LSQSURF_ASSIGN_OR_RETURN_IMPL_(LSQSURF_CONCAT_(lsqsurf_statusor_, __LINE__), lhs, expr)
#define LSQSURF_ASSIGN_OR_RETURN_IMPL_(tmp, lhs, expr) \
  auto tmp = (expr);                                   \
  if (!tmp.ok()) return std::move(tmp).status();       \
  lhs = std::move(tmp).value()
