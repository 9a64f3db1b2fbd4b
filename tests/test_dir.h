// tests/test_dir.h — a scratch folder per test.
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <string>

namespace lsqsurf::testing {

// An empty folder named after the prefix, the process and the running test (so parallel test
// processes never share one); the caller removes it.
inline std::filesystem::path FreshTestDir(const std::string& prefix) {
  const auto dir =
      std::filesystem::temp_directory_path() / (prefix + "-" + std::to_string(::getpid()) + "-" +
                                                ::testing::UnitTest::GetInstance()->current_test_info()->name());
  std::filesystem::remove_all(dir);
  return dir;
}

}  // namespace lsqsurf::testing
