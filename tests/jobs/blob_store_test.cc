#include "worker/jobs/blob_store.h"

#include <gtest/gtest.h>

#include <filesystem>

namespace lsqsurf::jobs {
namespace {

TEST(LocalDirBlobStore, StoresStreamsReplacesAndRemoves) {
  const auto root = std::filesystem::temp_directory_path() / ("lsqsurf-blobs-" + std::to_string(::getpid()));
  std::filesystem::remove_all(root);
  auto blobs = LocalDirBlobStore::Open(root.string());
  ASSERT_TRUE(blobs.ok()) << blobs.status();
  std::string bytes;
  for (int i = 0; i < 100000; ++i) bytes += static_cast<char>(i * 7 % 251);  // Binary, with zeros.
  ASSERT_TRUE((*blobs)->Put("job1", "mesh.drc", bytes).ok());
  EXPECT_TRUE((*blobs)->Exists("job1", "mesh.drc"));
  EXPECT_FALSE((*blobs)->Exists("job1", "other"));

  auto reader = (*blobs)->Open("job1", "mesh.drc");
  ASSERT_TRUE(reader.ok());
  EXPECT_EQ((*reader)->size(), 100000);
  std::string streamed;
  int chunks = 0;
  for (auto chunk = (*reader)->Next(30000); chunk.ok() && !chunk->empty(); chunk = (*reader)->Next(30000)) {
    EXPECT_LE(chunk->size(), 30000u);
    streamed += *chunk;
    ++chunks;
  }
  EXPECT_EQ(chunks, 4);
  EXPECT_EQ(streamed, bytes);

  ASSERT_TRUE((*blobs)->Put("job1", "mesh.drc", "short").ok());
  EXPECT_EQ((*blobs)->Read("job1", "mesh.drc").value(), "short");
  EXPECT_EQ((*blobs)->Open("job1", "nothing").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ((*blobs)->Open("job2", "mesh.drc").status().code(), absl::StatusCode::kNotFound);
  ASSERT_TRUE((*blobs)->RemoveJob("job1").ok());
  EXPECT_FALSE((*blobs)->Exists("job1", "mesh.drc"));
  EXPECT_TRUE((*blobs)->RemoveJob("job1").ok());  // Nothing left: not an error.
  std::filesystem::remove_all(root);
}

}  // namespace
}  // namespace lsqsurf::jobs
