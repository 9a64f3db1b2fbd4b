#include "server/limits.h"

#include <array>
#include <cmath>
#include <set>

#include "worker/core/strings.h"

namespace lsqsurf::server {
namespace {

using Options = jobs::JobServiceOptions;
constexpr double kMiB = double(int64_t{1} << 20), kGiB = double(int64_t{1} << 30);

// Bytes in MiB, with -1 (the option's "chosen for the machine") kept.
double ToMiB(int64_t bytes) { return bytes < 0 ? -1.0 : static_cast<double>(bytes) / kMiB; }
int64_t FromMiB(double mib) { return mib < 0 ? -1 : static_cast<int64_t>(std::llround(mib * kMiB)); }

const std::array<ServerLimit, 14> kLimits{{
    {"workers", "jobs that run at once", LimitUnit::kCount, 1, 64, true,
     [](const Options& o) { return double(o.workers); }, [](Options& o, double v) { o.workers = int(v); }, "workers",
     [](const Options& o) { return int64_t{o.workers}; }},
    {"max-queue", "queued jobs before submissions are refused", LimitUnit::kCount, 1, 100000, true,
     [](const Options& o) { return double(o.max_queue); }, [](Options& o, double v) { o.max_queue = int(v); },
     "max_queue", [](const Options& o) { return int64_t{o.max_queue}; }},
    {"max-points", "largest accepted cloud", LimitUnit::kCount, 16, 2e9, true,
     [](const Options& o) { return double(o.max_points); },
     [](Options& o, double v) { o.max_points = static_cast<int64_t>(v); }, "max_points",
     [](const Options& o) { return o.max_points; }},
    {"min-points", "smallest accepted surface cloud", LimitUnit::kCount, 4, 1e6, true,
     [](const Options& o) { return double(o.min_points); },
     [](Options& o, double v) { o.min_points = static_cast<int64_t>(v); }, "min_points",
     [](const Options& o) { return o.min_points; }},
    {"max-cells", "largest accepted volume mesh, in cells", LimitUnit::kCount, 1, 2e9, true,
     [](const Options& o) { return double(o.max_cells); },
     [](Options& o, double v) { o.max_cells = static_cast<int64_t>(v); }, "max_cells",
     [](const Options& o) { return o.max_cells; }},
    {"max-upload-mib", "largest accepted upload, MiB", LimitUnit::kMiB, 1, double(int64_t{1} << 20), true,
     [](const Options& o) { return ToMiB(o.max_input_bytes); },
     [](Options& o, double v) { o.max_input_bytes = FromMiB(v); }, "max_upload_bytes",
     [](const Options& o) { return o.max_input_bytes; }},
    {"max-renders", "pictures drawn at once by Render; more are refused", LimitUnit::kCount, 1, 64, true,
     [](const Options& o) { return double(o.max_renders); }, [](Options& o, double v) { o.max_renders = int(v); },
     "max_renders", [](const Options& o) { return int64_t{o.max_renders}; }},
    {"max-render-mib",
     "memory one picture of a volume field may take for its sampled grid (16 bytes a point); a resolution that "
     "needs more is refused",
     LimitUnit::kMiB, 16, double(int64_t{1} << 20), true, [](const Options& o) { return ToMiB(o.max_render_bytes); },
     [](Options& o, double v) { o.max_render_bytes = FromMiB(v); }, "", nullptr},
    {"max-job-mib",
     "memory one job may take, MiB: a job estimated to need more is refused at submission, and an extraction "
     "that grows past it stops; -1 = three quarters of the machine's (or container's) memory, 0 = no limit",
     LimitUnit::kMiB, -1, double(int64_t{1} << 30), true, [](const Options& o) { return ToMiB(o.max_job_memory); },
     [](Options& o, double v) { o.max_job_memory = FromMiB(v); }, "max_job_memory_bytes",
     [](const Options& o) { return o.max_job_memory; }},
    {"max-attempts", "starts cut short by a crash after which a job is failed (a graceful stop does not count)",
     LimitUnit::kCount, 1, 100, true, [](const Options& o) { return double(o.max_attempts); },
     [](Options& o, double v) { o.max_attempts = int(v); }, "", nullptr},
    {"lease-seconds",
     "a running job stays this server's this long without a renewal: how long the jobs of a server that died "
     "wait before another runs them",
     LimitUnit::kSeconds, 1, 3600, false,
     [](const Options& o) { return std::chrono::duration<double>(o.lease).count(); },
     [](Options& o, double v) { o.lease = std::chrono::milliseconds(std::llround(v * 1000)); }, "", nullptr},
    {"retain-days", "delete finished jobs this many days after they ended, oldest first (0: keep them until deleted)",
     LimitUnit::kDays, 0, 36500, false, [](const Options& o) { return double(o.retain.count()) / 86400; },
     [](Options& o, double v) { o.retain = std::chrono::seconds(std::llround(v * 86400)); }, "retain_seconds",
     [](const Options& o) { return static_cast<int64_t>(o.retain.count()); }},
    {"max-store-gib",
     "GiB all jobs may keep; past it the oldest finished jobs are deleted, then submissions refused (0: no "
     "limit)",
     LimitUnit::kGiB, 0, 1e6, false, [](const Options& o) { return double(o.max_store_bytes) / kGiB; },
     [](Options& o, double v) { o.max_store_bytes = static_cast<int64_t>(std::llround(v * kGiB)); }, "max_store_bytes",
     [](const Options& o) { return o.max_store_bytes; }},
    {"min-free-mib", "refuse submissions that would leave the data disk less than this free, for running jobs' results",
     LimitUnit::kMiB, 0, double(int64_t{1} << 30), true, [](const Options& o) { return ToMiB(o.min_free_bytes); },
     [](Options& o, double v) { o.min_free_bytes = FromMiB(v); }, "", nullptr},
}};

}  // namespace

std::span<const ServerLimit> ServerLimits() { return kLimits; }

std::string LimitText(const ServerLimit& limit, double value) {
  if (limit.integer) return core::StrCat(static_cast<int64_t>(std::llround(value)));
  return core::StrCat(value);
}

std::string LimitsReference(const jobs::JobServiceOptions& defaults) {
  static constexpr std::array<std::string_view, 5> kUnits{"count", "MiB", "GiB", "seconds", "days"};
  std::string out =
      "# lsqsurfd limits\n\nGenerated by `lsqsurfd --limits-reference` from server/limits.cc, one row per limit "
      "of the job service; a test checks this file against it. The stream and HTTP bounds are in the README's "
      "Security section.\n\n| flag | default | range | unit | what it bounds | reported by GetServerInfo as |\n"
      "|---|---|---|---|---|---|\n";
  for (const ServerLimit& limit : kLimits) {
    out += core::StrCat("| `--", limit.flag, "` | ", LimitText(limit, limit.get(defaults)), " | ",
                        LimitText(limit, limit.min), " to ", LimitText(limit, limit.max), " | ",
                        kUnits[static_cast<size_t>(limit.unit)], limit.integer ? "" : " (fractions allowed)", " | ",
                        limit.help, " | ",
                        limit.info_field.empty() ? std::string("—") : core::StrCat("`", limit.info_field, "`"), " |\n");
  }
  return out;
}

void ReportLimits(const jobs::JobServiceOptions& options, v1::ServerInfo& info) {
  const google::protobuf::Descriptor* descriptor = info.GetDescriptor();
  const google::protobuf::Reflection* reflection = info.GetReflection();
  for (const ServerLimit& limit : kLimits) {
    if (limit.info_field.empty()) continue;
    const google::protobuf::FieldDescriptor* field = descriptor->FindFieldByName(std::string(limit.info_field));
    if (field == nullptr) continue;  // CheckLimitTable (tests) refuses such a row.
    const int64_t value = limit.reported(options);
    if (field->cpp_type() == google::protobuf::FieldDescriptor::CPPTYPE_INT32) {
      reflection->SetInt32(&info, field, static_cast<int32_t>(value));
    } else if (field->cpp_type() == google::protobuf::FieldDescriptor::CPPTYPE_INT64) {
      reflection->SetInt64(&info, field, value);
    }
  }
}

absl::Status CheckLimitTable() {
  std::set<std::string_view> flags, fields;
  const google::protobuf::Descriptor* descriptor = v1::ServerInfo::descriptor();
  for (const ServerLimit& limit : kLimits) {
    if (!flags.insert(limit.flag).second) return absl::InternalError(core::StrCat("flag ", limit.flag, " twice"));
    if (limit.get == nullptr || limit.set == nullptr || !(limit.min <= limit.max)) {
      return absl::InternalError(core::StrCat("row ", limit.flag, " is incomplete"));
    }
    if (limit.info_field.empty()) continue;
    const google::protobuf::FieldDescriptor* field = descriptor->FindFieldByName(std::string(limit.info_field));
    const bool integer = field != nullptr && (field->cpp_type() == google::protobuf::FieldDescriptor::CPPTYPE_INT32 ||
                                              field->cpp_type() == google::protobuf::FieldDescriptor::CPPTYPE_INT64);
    if (!integer || limit.reported == nullptr || !fields.insert(limit.info_field).second) {
      return absl::InternalError(
          core::StrCat("row ", limit.flag, ": ServerInfo has no integer field ", limit.info_field, " of its own"));
    }
  }
  return absl::OkStatus();
}

}  // namespace lsqsurf::server
