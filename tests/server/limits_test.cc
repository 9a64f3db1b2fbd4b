// The limits table: well-formed, each row's flag value reaching its option and back, and
// GetServerInfo reporting what the options hold.
#include "server/limits.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>

#include "client/client.h"
#include "server/server.h"
#include "tests/test_dir.h"

namespace lsqsurf::server {
namespace {

TEST(LimitTable, EveryRowIsCompleteAndNamesAServerInfoFieldOfItsOwn) {
  const absl::Status checked = CheckLimitTable();
  EXPECT_TRUE(checked.ok()) << checked;
  EXPECT_GE(ServerLimits().size(), 10u);
}

// A value inside each row's range, not its default: set into the options, read back the same.
// Fractions are halves (leases keep milliseconds, retention seconds).
double Probe(const ServerLimit& limit) {
  const double value = limit.min + (limit.max - limit.min) / 7 + 1;
  return limit.integer ? std::floor(value) : std::floor(2 * value) / 2 + 0.5;
}

TEST(LimitTable, EachFlagValueReachesItsOptionAndComesBack) {
  for (const ServerLimit& limit : ServerLimits()) {
    jobs::JobServiceOptions options;
    const double probe = Probe(limit);
    ASSERT_NE(limit.get(options), probe) << limit.flag;
    limit.set(options, probe);
    EXPECT_NEAR(limit.get(options), probe, 1e-9 * std::abs(probe)) << limit.flag;
    // The others are left alone.
    const jobs::JobServiceOptions defaults;
    for (const ServerLimit& other : ServerLimits()) {
      if (other.flag == limit.flag) continue;
      EXPECT_EQ(other.get(options), other.get(defaults)) << limit.flag << " moved " << other.flag;
    }
  }
  // Units: 3 MiB of upload are 3 << 20 bytes; -1 (chosen for the machine) stays -1.
  jobs::JobServiceOptions options;
  for (const ServerLimit& limit : ServerLimits()) {
    if (limit.flag == "max-upload-mib") limit.set(options, 3);
    if (limit.flag == "max-job-mib") limit.set(options, -1);
    if (limit.flag == "retain-days") limit.set(options, 1.5);
  }
  EXPECT_EQ(options.max_input_bytes, 3 << 20);
  EXPECT_EQ(options.max_job_memory, -1);
  EXPECT_EQ(options.retain, std::chrono::seconds(129600));
}

TEST(LimitTable, GetServerInfoReportsEveryRowThatNamesAField) {
  const auto dir = testing::FreshTestDir("lsqsurf-limits");
  jobs::JobServiceOptions options;
  options.data_dir = dir.string();
  options.workers = 3;
  options.max_queue = 17;
  options.max_points = 123456;
  options.min_points = 9;
  options.max_cells = 7777;
  options.max_input_bytes = int64_t{5} << 20;
  options.max_renders = 3;
  options.max_job_memory = int64_t{900} << 20;
  options.retain = std::chrono::seconds(86400 * 3);
  options.max_store_bytes = int64_t{2} << 30;
  auto jobs = jobs::JobService::Open(options);
  ASSERT_TRUE(jobs.ok()) << jobs.status();
  auto server = Server::Start(**jobs, {});
  ASSERT_TRUE(server.ok()) << server.status();
  auto info = client::Client((*server)->address()).GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  int reported = 0;
  for (const ServerLimit& limit : ServerLimits()) {
    if (limit.info_field.empty()) continue;
    const auto* field = info->GetDescriptor()->FindFieldByName(std::string(limit.info_field));
    ASSERT_NE(field, nullptr) << limit.info_field;
    const int64_t value = field->cpp_type() == google::protobuf::FieldDescriptor::CPPTYPE_INT32
                              ? info->GetReflection()->GetInt32(*info, field)
                              : info->GetReflection()->GetInt64(*info, field);
    EXPECT_EQ(value, limit.reported(options)) << limit.flag;
    EXPECT_NE(value, limit.reported(jobs::JobServiceOptions{})) << limit.flag << " reports its default";
    ++reported;
  }
  EXPECT_GE(reported, 9);
  EXPECT_EQ(info->max_queue(), 17);  // Read as a client reads it.
  EXPECT_EQ(info->max_upload_bytes(), int64_t{5} << 20);
  server->reset();
  jobs->reset();
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace lsqsurf::server
