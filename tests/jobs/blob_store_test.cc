// The blob store contract, held by files in a folder and by chunks in PostgreSQL (on a
// throwaway server this test process starts).
#include "worker/jobs/store/blob_store.h"

#include <gtest/gtest.h>

#include <filesystem>

#if LSQSURF_WITH_POSTGRESQL
#include "tests/postgres_cluster.h"
#endif
#include "tests/test_dir.h"
#include "worker/io/files.h"
#if LSQSURF_WITH_POSTGRESQL
#include "worker/jobs/method_registry.h"
#include "worker/jobs/store/postgres_store.h"
#endif

namespace lsqsurf::jobs {
namespace {

class BlobStoreContract : public ::testing::TestWithParam<std::string> {
 protected:
  void SetUp() override {
    if (GetParam() == "files") {
      root_ = testing::FreshTestDir("lsqsurf-blobs");
      auto blobs = LocalDirBlobStore::Open(root_.string());
      ASSERT_TRUE(blobs.ok()) << blobs.status();
      blobs_ = *std::move(blobs);
      return;
    }
#if LSQSURF_WITH_POSTGRESQL
    std::string why_not;
    testing::PostgresCluster* cluster = testing::SharedPostgresCluster(&why_not);
    if (cluster == nullptr) GTEST_SKIP() << why_not;
    auto store = PostgresJobStore::Open(cluster->NewDatabase(), RegistrySpecTables());  // Makes the tables.
    ASSERT_TRUE(store.ok()) << store.status();
    blobs_ = std::make_unique<PostgresBlobStore>((*store)->pool());
#else
    GTEST_SKIP() << "built without PostgreSQL (LSQSURF_WITH_POSTGRESQL=OFF)";
#endif
  }
  void TearDown() override {
    if (!root_.empty()) std::filesystem::remove_all(root_);
  }
  std::filesystem::path root_;
  std::unique_ptr<BlobStore> blobs_;
};

// Sizes around the PostgreSQL store's chunk (files have none: any size tests them).
#if LSQSURF_WITH_POSTGRESQL
constexpr size_t kStoreChunk = PostgresBlobStore::kChunkBytes;
#else
constexpr size_t kStoreChunk = size_t{1} << 20;
#endif

std::string BinaryBytes(size_t n) {
  std::string bytes;
  bytes.reserve(n);
  for (size_t i = 0; i < n; ++i) bytes += static_cast<char>(i * 7 % 251);  // Binary, with zeros.
  return bytes;
}

TEST_P(BlobStoreContract, StoresStreamsReplacesAndRemoves) {
  const std::string bytes = BinaryBytes(100000);
  ASSERT_TRUE(blobs_->Put("job1", "mesh.drc", bytes).ok());
  EXPECT_TRUE(blobs_->Exists("job1", "mesh.drc"));
  EXPECT_FALSE(blobs_->Exists("job1", "other"));

  auto reader = blobs_->Open("job1", "mesh.drc");
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

  ASSERT_TRUE(blobs_->Put("job1", "mesh.drc", "short").ok());
  EXPECT_EQ(blobs_->Read("job1", "mesh.drc").value(), "short");
  EXPECT_EQ(blobs_->Open("job1", "nothing").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(blobs_->Open("job2", "mesh.drc").status().code(), absl::StatusCode::kNotFound);
  // One blob removed, the job's others kept.
  ASSERT_TRUE(blobs_->Put("job1", "tile-part-0", bytes).ok());
  ASSERT_TRUE(blobs_->Remove("job1", "tile-part-0").ok());
  EXPECT_FALSE(blobs_->Exists("job1", "tile-part-0"));
  EXPECT_EQ(blobs_->Read("job1", "mesh.drc").value_or(""), "short");
  EXPECT_TRUE(blobs_->Remove("job1", "tile-part-0").ok());  // Nothing left: not an error.
  ASSERT_TRUE(blobs_->RemoveJob("job1").ok());
  EXPECT_FALSE(blobs_->Exists("job1", "mesh.drc"));
  EXPECT_TRUE(blobs_->RemoveJob("job1").ok());  // Nothing left: not an error.
}

TEST_P(BlobStoreContract, LargeBlobsComeBackWhole) {
  // Several of the database's 1 MiB chunks, the last one partial, and an empty blob.
  const std::string bytes = BinaryBytes(kStoreChunk * 5 / 2);
  ASSERT_TRUE(blobs_->Put("job3", "input.drc", bytes).ok());
  auto back = blobs_->Read("job3", "input.drc");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(*back == bytes);
  ASSERT_TRUE(blobs_->Put("job3", "empty", "").ok());
  EXPECT_EQ(blobs_->Read("job3", "empty").value(), "");
}

TEST_P(BlobStoreContract, AReaderOfAReplacedBlobFailsRatherThanMixTwoVersions) {
  const std::string bytes = BinaryBytes(kStoreChunk * 2);
  ASSERT_TRUE(blobs_->Put("job4", "mesh.drc", bytes).ok());
  auto reader = blobs_->Open("job4", "mesh.drc");
  ASSERT_TRUE(reader.ok());
  auto first = (*reader)->Next(kStoreChunk);
  ASSERT_TRUE(first.ok());
  ASSERT_TRUE(blobs_->Put("job4", "mesh.drc", BinaryBytes(10)).ok());
  std::string rest;
  absl::Status status;
  for (;;) {
    auto chunk = (*reader)->Next(kStoreChunk);
    if (!chunk.ok()) {
      status = chunk.status();
      break;
    }
    if (chunk->empty()) break;
    rest += *chunk;
  }
  // Either the old version whole (files: the open file outlives its replacement) or an error.
  if (status.ok()) {
    EXPECT_TRUE(*first + rest == bytes);
  } else {
    EXPECT_EQ(status.code(), absl::StatusCode::kUnavailable);
  }
}

// A spool file handed over by path: its bytes come back whole, through Read and Map, and it is
// the store's now (the file store takes it by rename; another copies it and leaves it).
TEST_P(BlobStoreContract, AFileHandedOverComesBackWholeAndMapped) {
  const std::filesystem::path spool = testing::FreshTestDir("lsqsurf-spool");
  std::filesystem::create_directories(spool);
  const std::string path = (spool / "upload.input").string();
  const std::string bytes = BinaryBytes(kStoreChunk * 3 / 2);
  ASSERT_TRUE(io::WriteFileAtomically(path, bytes).ok());
  ASSERT_TRUE(blobs_->PutFile("job5", "input.drc", path).ok());
  if (GetParam() == "files") {
    EXPECT_FALSE(std::filesystem::exists(path)) << "taken by rename, not copied";
  }
  EXPECT_TRUE(blobs_->Read("job5", "input.drc").value() == bytes);
  auto mapped = blobs_->Map("job5", "input.drc");
  ASSERT_TRUE(mapped.ok()) << mapped.status();
  EXPECT_TRUE(mapped->view() == bytes);
  EXPECT_TRUE(mapped->movable_path().empty()) << "a stored blob is never handed on by rename";
  std::filesystem::remove(path);  // Where the store copied it, its caller removes it.
  EXPECT_EQ(blobs_->PutFile("job5", "other", path).code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(blobs_->Map("job5", "missing").status().code(), absl::StatusCode::kNotFound);
  std::filesystem::remove_all(spool);
}

INSTANTIATE_TEST_SUITE_P(Stores, BlobStoreContract, ::testing::Values("files", "postgresql"),
                         [](const ::testing::TestParamInfo<std::string>& param) { return param.param; });

}  // namespace
}  // namespace lsqsurf::jobs
