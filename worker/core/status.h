// worker/core/status.h — error propagation between modules.
//
// Modules return `absl::Status` / `absl::StatusOr<T>`; the 2022 abseil shipped with Debian lacks
// the return-if-error helper, so this macro stands in for it.
#pragma once

#include "absl/status/status.h"
#include "absl/status/statusor.h"

// Returns from the enclosing function when `expr` (an absl::Status) is not OK.
#define LSQSURF_RETURN_IF_ERROR(expr)                          \
  do {                                                         \
    if (absl::Status lsqsurf_status_ = (expr); !lsqsurf_status_.ok()) \
      return lsqsurf_status_;                                  \
  } while (false)
