// The job service's parts on their own: the decoded-input budget, the record table against a
// SQLite store (what watchers see is stored first; a write the store refuses stops the run; a
// cancellation reaches a held run), and retention (oldest first, by size and by age, files and
// records both gone).
#include <gtest/gtest.h>

#include <filesystem>
#include <future>
#include <thread>

#include "tests/test_dir.h"
#include "worker/jobs/job_retention.h"
#include "worker/jobs/job_table.h"
#include "worker/jobs/method_registry.h"
#include "worker/jobs/store/blob_store.h"
#include "worker/jobs/store/job_store.h"

namespace lsqsurf::jobs {
namespace {

using std::chrono::milliseconds;

JobRecord Record(const std::string& id, int64_t created_ms, JobState state = JobState::kQueued) {
  JobRecord r;
  r.id = id;
  r.spec.method = "iamls";
  r.spec.params = DefaultParams("iamls").value();
  r.state = state;
  r.created_ms = r.updated_ms = created_ms;
  r.input_bytes = 100;
  r.stored_bytes = 100;
  return r;
}

TEST(DecodedInputs, KeepsOnlyWhatItsBudgetHolds) {
  DecodedInputs decoded(100);
  EXPECT_TRUE(decoded.Keep("a", std::make_shared<DecodedInput>(), 60));
  EXPECT_FALSE(decoded.Keep("b", std::make_shared<DecodedInput>(), 50));  // 110 > 100.
  EXPECT_FALSE(decoded.Keep("c", nullptr, 1));                            // Nothing to keep.
  EXPECT_NE(decoded.Take("a"), nullptr);
  EXPECT_EQ(decoded.Take("a"), nullptr);                                 // Taken once.
  EXPECT_TRUE(decoded.Keep("b", std::make_shared<DecodedInput>(), 50));  // The budget is back.
  EXPECT_EQ(decoded.Take("unknown"), nullptr);
}

class JobPartsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTestDir("lsqsurf-parts");
    std::filesystem::create_directories(dir_);
    auto store = SqliteJobStore::Open((dir_ / "jobs.db").string(), RegistrySpecTables());
    ASSERT_TRUE(store.ok()) << store.status();
    store_ = *std::move(store);
    auto blobs = LocalDirBlobStore::Open((dir_ / "jobs").string());
    ASSERT_TRUE(blobs.ok()) << blobs.status();
    blobs_ = *std::move(blobs);
    table_ = std::make_unique<JobTable>(store_, decoded_);
  }
  void TearDown() override {
    table_.reset();
    store_.reset();
    std::filesystem::remove_all(dir_);
  }
  // A job inserted queued and claimed by `runner_`, held in the table.
  std::shared_ptr<JobEntry> HeldJob(const std::string& id) {
    EXPECT_TRUE(store_->Insert(Record(id, 1)).ok());
    auto claimed = store_->Claim(runner_, milliseconds(60'000));
    EXPECT_TRUE(claimed.ok() && claimed->has_value());
    return table_->Hold(**std::move(claimed));
  }
  // Every record on file into the table, as a starting service takes them.
  void LoadStore() {
    auto all = store_->ChangesSince(0);
    ASSERT_TRUE(all.ok()) << all.status();
    table_->Locked([&](const JobEntries&) {
      for (JobRecord& r : all->changed) table_->AdoptLocked(std::move(r));
      return 0;
    });
  }

  std::filesystem::path dir_;
  std::shared_ptr<JobStore> store_;
  std::shared_ptr<BlobStore> blobs_;
  DecodedInputs decoded_{1000};
  std::unique_ptr<JobTable> table_;
  const std::string runner_ = "parts-test/1";
};

TEST_F(JobPartsTest, ABuildsChildrenAreFoundByTheirParentAndGoWithTheirRecords) {
  auto child = [](const std::string& id, const std::string& parent, JobState state) {
    JobRecord r = Record(id, 2, state);
    r.parent = parent;
    return r;
  };
  table_->Locked([&](const JobEntries&) {
    table_->AdoptLocked(Record("p", 1, JobState::kRunning));
    table_->AdoptLocked(child("p-t1", "p", JobState::kSucceeded));
    table_->AdoptLocked(child("p-t0", "p", JobState::kRunning));
    table_->AdoptLocked(child("q-t0", "q", JobState::kQueued));
    return 0;
  });
  auto any_queued = [&](const std::string& parent) {
    return !table_
                ->Children(
                    parent, [](const JobRecord& r) { return r.state == JobState::kQueued; }, 1)
                .empty();
  };
  auto ids = [&](const std::string& parent) {
    std::vector<std::string> out;
    for (const JobRecord& r : table_->Children(parent)) out.push_back(r.id + ":" + std::string(JobStateName(r.state)));
    return out;
  };
  EXPECT_EQ(ids("p"), (std::vector<std::string>{"p-t0:running", "p-t1:succeeded"}));
  ASSERT_EQ(table_->Children("p", nullptr, 1).size(), 1u);
  EXPECT_EQ(table_->Children("p", nullptr, 1)[0].id, "p-t0");
  EXPECT_EQ(ids("q"), (std::vector<std::string>{"q-t0:queued"}));
  EXPECT_TRUE(ids("p-t0").empty());  // A child has no children; a top-level job is nobody's.
  EXPECT_FALSE(any_queued("p"));
  EXPECT_TRUE(any_queued("q"));
  // A newer record of a child changes what its parent sees; an erased child is gone from it.
  table_->Locked([&](const JobEntries&) {
    JobRecord requeued = child("p-t0", "p", JobState::kQueued);
    requeued.seq = 5;
    table_->AdoptLocked(requeued);
    table_->EraseLocked("p-t1");
    table_->EraseLocked("q-t0");
    table_->EraseLocked("never-known");
    return 0;
  });
  EXPECT_EQ(ids("p"), (std::vector<std::string>{"p-t0:queued"}));
  EXPECT_TRUE(any_queued("p"));
  EXPECT_TRUE(ids("q").empty());
  EXPECT_FALSE(any_queued("q"));
  EXPECT_EQ(table_->List().size(), 1u);  // Children stay out of the listing.
}

TEST_F(JobPartsTest, AWatcherSeesAChangeOnlyOnceTheStoreHasIt) {
  const std::shared_ptr<JobEntry> entry = HeldJob("job-a");
  ASSERT_TRUE(entry->held);
  const uint64_t version = table_->Snapshot(*entry).version;
  std::promise<JobRecord> seen;
  std::thread watcher([&] {
    auto r = table_->WaitForChange("job-a", version, milliseconds(30'000));
    // What the watcher is shown is in the store already.
    auto stored = store_->Get("job-a");
    EXPECT_TRUE(stored.ok());
    if (stored.ok()) {
      EXPECT_EQ(stored->stage, "fitting");
    }
    seen.set_value(r.ok() ? *r : JobRecord{});
  });
  table_->Update(entry, [](JobRecord& r) {
    r.stage = "fitting";
    r.progress = 0.5;
  });
  const JobRecord r = seen.get_future().get();
  watcher.join();
  EXPECT_EQ(r.stage, "fitting");
  EXPECT_DOUBLE_EQ(r.progress, 0.5);
  EXPECT_GT(r.version, version);
}

TEST_F(JobPartsTest, AWriteTheStoreRefusesStopsTheRunAndTheStoresStateStands) {
  const std::shared_ptr<JobEntry> entry = HeldJob("job-b");
  // The store gives the job back to the queue as if this runner's lease had lapsed.
  auto recovered = store_->RecoverLapsed(true, [](JobRecord& r) { r.state = JobState::kQueued; });
  ASSERT_TRUE(recovered.ok()) << recovered.status();
  ASSERT_EQ(recovered->size(), 1u);
  EXPECT_FALSE(entry->lost);
  table_->Update(entry, [](JobRecord& r) { r.progress = 0.9; });
  EXPECT_TRUE(entry->lost) << "a write refused as not held must stop the run";
  table_->Release(entry);
  EXPECT_FALSE(entry->held);
  auto r = table_->Get("job-b");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->state, JobState::kQueued);  // The store's, not the run's view.
}

TEST_F(JobPartsTest, ACancellationReachesAHeldRun) {
  const std::shared_ptr<JobEntry> entry = HeldJob("job-c");
  auto r = table_->Cancel("job-c");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->state, JobState::kRunning);
  EXPECT_TRUE(entry->cancel_requested);
  EXPECT_FALSE(table_->Cancel("no-such-job").ok());
}

TEST_F(JobPartsTest, RetentionDeletesTheOldestFinishedJobsBySizeThenByAge) {
  for (int i = 0; i < 3; ++i) {
    const std::string id = "done-" + std::to_string(i);
    ASSERT_TRUE(store_->Insert(Record(id, 1000 * (i + 1), JobState::kSucceeded)).ok());
    ASSERT_TRUE(blobs_->Put(id, "mesh.drc", "bytes").ok());
  }
  ASSERT_TRUE(store_->Insert(Record("queued", 500)).ok());  // Never deleted, however old.
  LoadStore();
  JobRetention size_limited({std::chrono::seconds(0), 300, milliseconds(60'000)}, *table_, *store_, *blobs_);
  EXPECT_EQ(size_limited.RecordedBytes(), 400);
  // 400 bytes kept, 300 allowed: the oldest finished job goes, and only it.
  EXPECT_EQ(size_limited.SweepFinished(10'000), 1);
  EXPECT_FALSE(table_->Get("done-0").ok());
  EXPECT_EQ(store_->Get("done-0").status().code(), absl::StatusCode::kNotFound);
  EXPECT_FALSE(blobs_->Exists("done-0", "mesh.drc"));
  EXPECT_TRUE(blobs_->Exists("done-1", "mesh.drc"));
  EXPECT_EQ(size_limited.RecordedBytes(), 300);
  // Room asked for: one more goes.
  EXPECT_EQ(size_limited.SweepFinished(10'000, 100), 1);
  EXPECT_TRUE(table_->Get("done-2").ok());

  JobRetention age_limited({std::chrono::seconds(10), 0, milliseconds(60'000)}, *table_, *store_, *blobs_);
  EXPECT_EQ(age_limited.SweepFinished(3000 + 10'000), 0);  // Ended 10 s ago: kept.
  EXPECT_EQ(age_limited.SweepFinished(3000 + 10'001), 1);
  EXPECT_TRUE(table_->Get("queued").ok());
  EXPECT_EQ(age_limited.Delete("queued").code(), absl::StatusCode::kFailedPrecondition);
}

}  // namespace
}  // namespace lsqsurf::jobs
