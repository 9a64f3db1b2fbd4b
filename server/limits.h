// server/limits.h — the job service's limits, declared once: each row makes its lsqsurfd flag
// (name, help, unit, range, default from JobServiceOptions), says which GetServerInfo field
// reports it, and the README's Security table is checked against the rows (tests/server). A new
// limit is a field in JobServiceOptions and one row here.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "lsqsurf/v1/reconstruction.pb.h"
#include "worker/jobs/job_service.h"

namespace lsqsurf::server {

// What a flag's number counts; the options hold bytes and durations.
enum class LimitUnit { kCount, kMiB, kGiB, kSeconds, kDays };

struct ServerLimit {
  std::string_view flag;  // Without its dashes: "max-queue".
  std::string_view help;
  LimitUnit unit = LimitUnit::kCount;
  double min = 0, max = 0;  // In the flag's unit.
  bool integer = true;      // Whole numbers only.
  // The value in the flag's unit, and setting it from one.
  double (*get)(const jobs::JobServiceOptions&) = nullptr;
  void (*set)(jobs::JobServiceOptions&, double) = nullptr;
  // The ServerInfo field that reports it (in bytes or seconds, as the proto says), or empty; and
  // that value.
  std::string_view info_field;
  int64_t (*reported)(const jobs::JobServiceOptions&) = nullptr;
};

std::span<const ServerLimit> ServerLimits();

// A row's value as its flag's default shows it ("64", "0.5").
std::string LimitText(const ServerLimit& limit, double value);

// The rows as docs/limits.md holds them: a Markdown table with the defaults of `defaults`.
std::string LimitsReference(const jobs::JobServiceOptions& defaults);

// Sets the ServerInfo field of every row that names one.
void ReportLimits(const jobs::JobServiceOptions& options, v1::ServerInfo& info);

// Whether every row's info_field is an integer field of ServerInfo, and no two rows name one.
// Errors: kInternal naming the row.
absl::Status CheckLimitTable();

}  // namespace lsqsurf::server
