// Mapped bytes and moving files into place: what the upload path builds on to keep uploads off
// the heap.
#include "worker/io/files.h"

#include <gtest/gtest.h>
#include <sys/stat.h>

#include <filesystem>
#include <string>

#include "tests/test_dir.h"
#include "worker/core/byte_view.h"

namespace lsqsurf::io {
namespace {

class FilesTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-files");
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }
  std::string PathOf(const std::string& name) const { return (dir_ / name).string(); }
  std::filesystem::path dir_;
};

std::string Pattern(size_t n) {
  std::string bytes(n, '\0');
  for (size_t i = 0; i < n; ++i) bytes[i] = static_cast<char>((i * 131 + i / 4099) % 256);
  return bytes;
}

TEST_F(FilesTest, AMappedFileReadsAsItsBytesAndOutlivesTheFileName) {
  const std::string bytes = Pattern(3 * 4096 + 17);  // Not a whole number of pages.
  ASSERT_TRUE(WriteFileAtomically(PathOf("a"), bytes).ok());
  auto mapped = core::ByteView::MapFile(PathOf("a"));
  ASSERT_TRUE(mapped.ok()) << mapped.status();
  EXPECT_EQ(mapped->size(), bytes.size());
  EXPECT_TRUE(mapped->view() == bytes);
  EXPECT_TRUE(mapped->movable_path().empty());
  const core::ByteView copy = *mapped;  // Shares the mapping.
  std::filesystem::rename(PathOf("a"), PathOf("b"));
  std::filesystem::remove(PathOf("b"));
  EXPECT_TRUE(copy.view() == bytes) << "the mapping holds the file after it is renamed and removed";
}

TEST_F(FilesTest, MappingAnEmptyOrMissingFile) {
  ASSERT_TRUE(WriteFileAtomically(PathOf("empty"), "").ok());
  auto empty = core::ByteView::MapFile(PathOf("empty"), /*movable=*/true);
  ASSERT_TRUE(empty.ok()) << empty.status();
  EXPECT_TRUE(empty->empty());
  EXPECT_EQ(empty->movable_path(), PathOf("empty"));
  EXPECT_EQ(core::ByteView::MapFile(PathOf("missing")).status().code(), absl::StatusCode::kNotFound);
  const core::ByteView held(std::string("in memory"));
  EXPECT_EQ(held.view(), "in memory");
  EXPECT_TRUE(held.movable_path().empty());
}

TEST_F(FilesTest, AMoveRenamesWithinAFileSystem) {
  const std::string bytes = Pattern(70000);
  ASSERT_TRUE(WriteFileAtomically(PathOf("from"), bytes).ok());
  struct stat before {};
  ASSERT_EQ(::stat(PathOf("from").c_str(), &before), 0);
  ASSERT_TRUE(MoveFileAtomically(PathOf("from"), PathOf("to")).ok());
  EXPECT_FALSE(std::filesystem::exists(PathOf("from")));
  struct stat after {};
  ASSERT_EQ(::stat(PathOf("to").c_str(), &after), 0);
  EXPECT_EQ(before.st_ino, after.st_ino) << "renamed, not copied";
  EXPECT_TRUE(ReadFileBytes(PathOf("to")).value() == bytes);
  EXPECT_EQ(MoveFileAtomically(PathOf("from"), PathOf("to")).code(), absl::StatusCode::kNotFound);
}

TEST_F(FilesTest, AMoveAcrossFileSystemsCopiesAndRemoves) {
  // /dev/shm is a tmpfs on Linux; where it shares the temporary folder's file system there is
  // no second one to move across.
  const std::filesystem::path shm = "/dev/shm";
  struct stat temp_info {
  }, shm_info{};
  if (::stat(dir_.c_str(), &temp_info) != 0 || ::stat(shm.c_str(), &shm_info) != 0 ||
      temp_info.st_dev == shm_info.st_dev) {
    GTEST_SKIP() << "no second file system beside " << dir_;
  }
  const std::string from = (shm / ("lsqsurf-move-" + std::to_string(::getpid()))).string();
  const std::string bytes = Pattern(200000);
  ASSERT_TRUE(WriteFileAtomically(from, bytes).ok());
  const absl::Status moved = MoveFileAtomically(from, PathOf("to"));
  EXPECT_TRUE(moved.ok()) << moved;
  EXPECT_FALSE(std::filesystem::exists(from));
  EXPECT_TRUE(ReadFileBytes(PathOf("to")).value() == bytes);
  std::filesystem::remove(from);
}

}  // namespace
}  // namespace lsqsurf::io
