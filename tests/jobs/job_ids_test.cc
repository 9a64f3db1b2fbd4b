// Job ids: drawn from the kernel's generator (getrandom is interposed here to see that every id
// is exactly 16 of its bytes), well formed, and with no bias a simple check would see.
#include "worker/jobs/job_ids.h"

#include <gtest/gtest.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cmath>
#include <cstring>
#include <set>
#include <string>

namespace {

// While set, getrandom hands out these bytes instead of the kernel's.
std::atomic<const unsigned char*> scripted{nullptr};
std::atomic<int> calls{0};

}  // namespace

// The executable's definition takes the place of the C library's for the whole process.
extern "C" ssize_t getrandom(void* buffer, size_t length, unsigned int flags) {
  ++calls;
  if (const unsigned char* bytes = scripted.load()) {
    std::memcpy(buffer, bytes, length);
    return static_cast<ssize_t>(length);
  }
  return syscall(SYS_getrandom, buffer, length, flags);
}

namespace lsqsurf::jobs {
namespace {

TEST(JobIds, AreSixteenBytesOfTheKernelsGenerator) {
  std::array<unsigned char, 16> bytes;
  for (size_t i = 0; i < bytes.size(); ++i) bytes[i] = static_cast<unsigned char>(0x0f * i + 0x5a);
  const int before = calls.load();
  scripted = bytes.data();
  const std::string id = NewJobId();
  scripted = nullptr;
  EXPECT_EQ(calls.load() - before, 1);
  EXPECT_EQ(id, "5a69788796a5b4c3d2e1f0ff0e1d2c3b");
}

TEST(JobIds, TenThousandAreDistinctWellFormedAndUnbiased) {
  constexpr int kIds = 10'000;
  std::set<std::string> seen;
  std::array<int, 128> ones_at{};  // Per bit position.
  int64_t ones = 0, changes = 0;   // All bits; bits that differ from the previous id's.
  std::string previous;
  for (int n = 0; n < kIds; ++n) {
    const std::string id = NewJobId();
    ASSERT_TRUE(IsJobIdForm(id)) << id;
    ASSERT_EQ(id.size(), 32u);
    ASSERT_TRUE(seen.insert(id).second) << "repeated " << id;
    for (int d = 0; d < 32; ++d) {
      const int nibble = id[d] <= '9' ? id[d] - '0' : id[d] - 'a' + 10;
      const int before = previous.empty() ? 0 : (previous[d] <= '9' ? previous[d] - '0' : previous[d] - 'a' + 10);
      for (int b = 0; b < 4; ++b) {
        const int bit = (nibble >> b) & 1;
        ones_at[static_cast<size_t>(4 * d + b)] += bit;
        ones += bit;
        if (!previous.empty()) changes += bit != ((before >> b) & 1);
      }
    }
    previous = id;
  }
  // Monobit over 1.28M bits, and the serial test (each bit flips half the time from one id to the
  // next), within 5 standard deviations; each position over 10k ids within 5 as well.
  const double total = 128.0 * kIds, sigma = 0.5 / std::sqrt(total);
  EXPECT_NEAR(static_cast<double>(ones) / total, 0.5, 5 * sigma);
  EXPECT_NEAR(static_cast<double>(changes) / (128.0 * (kIds - 1)), 0.5, 5 * sigma);
  for (size_t b = 0; b < ones_at.size(); ++b) {
    EXPECT_NEAR(ones_at[b] / double{kIds}, 0.5, 5 * 0.5 / std::sqrt(double{kIds})) << "bit " << b;
  }
}

TEST(JobIds, OnlyIdsAndArtifactNamesOfTheirFormPass) {
  EXPECT_TRUE(IsJobIdForm("0123456789abcdef0123456789abcdef"));
  EXPECT_TRUE(IsJobIdForm("0123456789abcdef"));  // Ids of earlier versions.
  for (const char* bad : {"", "0123456789ABCDEF", "0123456789abcde", "0123456789abcdef0", "../../etc/passwd",
                          "0123456789abcde\n", "0123456789abcdef0123456789abcdeg"}) {
    EXPECT_FALSE(IsJobIdForm(bad)) << bad;
  }
  for (const char* good : {"mesh.drc", "frame_00100.drc", "preview.png", "function.lqpu", "values.csv"}) {
    EXPECT_TRUE(IsArtifactNameForm(good)) << good;
  }
  for (const std::string& bad : {std::string(), std::string(".hidden"), std::string("../mesh.drc"), std::string("a/b"),
                                 std::string("line\nbreak"), std::string(129, 'a')}) {
    EXPECT_FALSE(IsArtifactNameForm(bad)) << bad;
  }
}

}  // namespace
}  // namespace lsqsurf::jobs
