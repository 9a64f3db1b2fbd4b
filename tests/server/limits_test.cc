// The limits table: well-formed, each row's flag value reaching its option and back, and
// GetServerInfo reporting what the options hold.
#include "server/limits.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "client/client.h"
#include "server/server.h"
#include "tests/test_dir.h"
#include "worker/core/strings.h"

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

// A proto line declaring a field, "  int64 max_points = 2;": its type and name, or empty.
std::pair<std::string, std::string> FieldDeclared(const std::string& line) {
  std::istringstream words(line);
  std::string type, name, equals, number, rest;
  if (!(words >> type >> name >> equals >> number) || (words >> rest) || equals != "=" || type.starts_with("//") ||
      number.size() < 2 || number.back() != ';') {
    return {};
  }
  return {type, name};
}

// The comment over each reported field (or over the run of fields it belongs to) in the proto
// names the flag that sets it, so that a client author finds the knob behind a number.
TEST(LimitTable, TheProtoCommentOfEachReportedFieldNamesItsFlag) {
  std::ifstream in(LSQSURF_SOURCE_DIR "/proto/lsqsurf/v1/reconstruction.proto");
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  ASSERT_GT(lines.size(), 100u);
  const auto is_comment = [](const std::string& line) {
    const size_t first = line.find_first_not_of(' ');
    return first != std::string::npos && line.compare(first, 2, "//") == 0;
  };
  int checked = 0;
  for (const ServerLimit& limit : ServerLimits()) {
    if (limit.info_field.empty()) continue;
    size_t at = 0;
    for (; at < lines.size(); ++at) {
      const auto [type, name] = FieldDeclared(lines[at]);
      if (name == limit.info_field && (type == "int32" || type == "int64")) break;
    }
    ASSERT_LT(at, lines.size()) << "no integer field " << limit.info_field;
    size_t above = at;
    while (above > 0 && !FieldDeclared(lines[above - 1]).second.empty()) --above;  // Its run of fields.
    std::string comment;
    while (above > 0 && is_comment(lines[above - 1])) comment = lines[--above] + "\n" + comment;
    EXPECT_NE(comment.find(core::StrCat("--", limit.flag)), std::string::npos)
        << limit.info_field << "'s comment does not name --" << limit.flag << ":\n"
        << comment;
    ++checked;
  }
  EXPECT_GE(checked, 9);
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
