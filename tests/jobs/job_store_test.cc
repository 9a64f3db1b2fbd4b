// The job store contract, held by both stores: SQLite (one server) and PostgreSQL (shared, on a
// throwaway server this test process starts). Two "servers" are two runner names; on PostgreSQL
// they also use two store objects, i.e. two connection pools, as two processes would.
#include "worker/jobs/store/job_store.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <future>
#include <set>
#include <thread>

#include "absl/strings/match.h"
#if LSQSURF_WITH_POSTGRESQL
#include "tests/postgres_cluster.h"
#endif
#include "tests/test_dir.h"
#include "tests/test_shapes.h"
#include "worker/core/strings.h"
#include "worker/jobs/job_replication.h"
#include "worker/jobs/method_registry.h"
#if LSQSURF_WITH_POSTGRESQL
#include "worker/jobs/store/postgres_store.h"
#endif
#include "worker/jobs/tile_exchange.h"

namespace lsqsurf::jobs {
namespace {

using std::chrono::milliseconds;

// Tables of this build's format that know no method; the methods asked for go to `asked`.
SpecTables WithoutMethods(std::vector<std::string>* asked) {
  return {[asked](std::string_view method) -> absl::StatusOr<core::ParamSet> {
            asked->emplace_back(method);
            return absl::InvalidArgumentError("no methods in this build");
          },
          DefaultView, kSpecFormat};
}

JobRecord Queued(const std::string& id, int64_t created_ms) {
  JobRecord r;
  r.id = id;
  r.spec.method = "iamls";
  r.spec.params = DefaultParams("iamls").value();
  r.created_ms = r.updated_ms = created_ms;
  r.input_points = 1234;
  r.input_bytes = 5678;
  return r;
}

class JobStoreContract : public ::testing::TestWithParam<std::string> {
 protected:
  void SetUp() override {
    if (GetParam() == "sqlite") {
      dir_ = testing::FreshTestDir("lsqsurf-store");
      std::filesystem::create_directories(dir_);
      auto store = SqliteJobStore::Open((dir_ / "jobs.db").string(), RegistrySpecTables());
      ASSERT_TRUE(store.ok()) << store.status();
      first_ = *std::move(store);
      second_ = first_;  // One server: both names share the one store.
      return;
    }
#if LSQSURF_WITH_POSTGRESQL
    std::string why_not;
    testing::PostgresCluster* cluster = testing::SharedPostgresCluster(&why_not);
    if (cluster == nullptr) GTEST_SKIP() << why_not;
    url_ = cluster->NewDatabase();
    ASSERT_FALSE(url_.empty());
    auto a = PostgresJobStore::Open(url_, RegistrySpecTables());
    ASSERT_TRUE(a.ok()) << a.status();
    auto b = PostgresJobStore::Open(url_, RegistrySpecTables());  // Migrating an up-to-date database changes nothing.
    ASSERT_TRUE(b.ok()) << b.status();
    first_ = *std::move(a);
    second_ = *std::move(b);
#else
    GTEST_SKIP() << "built without PostgreSQL (LSQSURF_WITH_POSTGRESQL=OFF)";
#endif
  }
  void TearDown() override {
    first_.reset();
    second_.reset();
    if (!dir_.empty()) std::filesystem::remove_all(dir_);
  }

  // Another store over the same database, reading specs with `tables`.
  std::shared_ptr<JobStore> Reopen(SpecTables tables) {
#if LSQSURF_WITH_POSTGRESQL
    if (!url_.empty()) {
      auto store = PostgresJobStore::Open(url_, std::move(tables));
      return store.ok() ? std::shared_ptr<JobStore>(*std::move(store)) : nullptr;
    }
#endif
    auto store = SqliteJobStore::Open((dir_ / "jobs.db").string(), std::move(tables));
    return store.ok() ? std::shared_ptr<JobStore>(*std::move(store)) : nullptr;
  }

  std::filesystem::path dir_;
  std::string url_;
  std::shared_ptr<JobStore> first_, second_;
};

TEST_P(JobStoreContract, RecordsRoundTripAndIdsAreUnique) {
  JobRecord r = Queued("a1", 100);
  r.statistics = {{"points", 1234}, {"wall_seconds", 0.125}};
  r.results = {"mesh.drc", "preview.png"};
  r.spec.preview.enabled = true;
  r.spec.preview.view = DefaultView();
  ASSERT_TRUE(r.spec.preview.view.Set("azimuth_deg", 30).ok());
  r.spec.preview.turntable_deg_per_frame = 2.5;
  r.spec.mesh_position_bits = 20;
  r.owner = "alice@example";
  r.stored_bytes = 9012;
  ASSERT_TRUE(first_->Insert(r).ok());
  EXPECT_EQ(first_->Insert(r).code(), absl::StatusCode::kAlreadyExists);
  auto back = second_->Get("a1");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->spec.method, "iamls");
  EXPECT_EQ(back->spec.params.Encode(), r.spec.params.Encode());
  EXPECT_EQ(back->spec.mesh_position_bits, 20);
  EXPECT_EQ(back->state, JobState::kQueued);
  EXPECT_EQ(back->created_ms, 100);
  EXPECT_EQ(back->input_points, 1234);
  EXPECT_EQ(back->input_bytes, 5678);
  EXPECT_EQ(back->owner, "alice@example");
  EXPECT_EQ(back->stored_bytes, 9012);
  EXPECT_EQ(back->statistics, r.statistics);
  EXPECT_EQ(back->results, r.results);
  EXPECT_TRUE(back->spec.preview.enabled);
  EXPECT_EQ(back->spec.preview.view.Get("azimuth_deg"), 30);
  EXPECT_EQ(back->spec.preview.turntable_deg_per_frame, 2.5);
  EXPECT_GT(back->seq, 0);
  EXPECT_EQ(second_->Get("nothing").status().code(), absl::StatusCode::kNotFound);

  // Text parameters come back byte for byte, control bytes and separators included (a NUL once
  // cut the stored spec short, so that the job came back after a restart as another).
  JobRecord text = Queued("a2", 101);
  text.spec.method = "csg";
  text.spec.params = DefaultParams("csg").value();
  const std::string expression(
      "sphere(r=1)\0;x=%41\n\x7f\x01"
      "end",
      24);
  ASSERT_TRUE(text.spec.params.SetText("expression", expression).ok());
  text.quota_bytes = int64_t{5} << 30;
  ASSERT_TRUE(first_->Insert(text).ok());
  auto text_back = second_->Get("a2");
  ASSERT_TRUE(text_back.ok()) << text_back.status();
  EXPECT_EQ(text_back->spec.params.GetText("expression").value_or(""), expression);
  EXPECT_EQ(text_back->quota_bytes, int64_t{5} << 30);
}

// The store knows no method: a stored spec is read with the tables it was given, so that a build
// without the method fails the job that still waits for it, and leaves a finished one as it was.
TEST_P(JobStoreContract, StoredSpecsAreReadWithTheTablesTheStoreWasGiven) {
  ASSERT_TRUE(first_->Insert(Queued("waiting", 100)).ok());
  JobRecord finished = Queued("finished", 101);
  finished.state = JobState::kSucceeded;
  finished.results = {"mesh.drc"};
  ASSERT_TRUE(first_->Insert(finished).ok());

  std::vector<std::string> asked;
  SpecTables without_methods = WithoutMethods(&asked);
  std::shared_ptr<JobStore> other = Reopen(std::move(without_methods));
  ASSERT_NE(other, nullptr);
  auto waiting = other->Get("waiting");
  ASSERT_TRUE(waiting.ok()) << waiting.status();
  EXPECT_EQ(waiting->state, JobState::kFailed);
  EXPECT_TRUE(absl::StrContains(waiting->error, "no method 'iamls'")) << waiting->error;
  EXPECT_EQ(asked, std::vector<std::string>{"iamls"});
  auto kept = other->Get("finished");
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_EQ(kept->state, JobState::kSucceeded);
  EXPECT_EQ(kept->results, finished.results);

  // With the registry's tables the same row reads back as it was stored.
  auto again = first_->Get("waiting");
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->state, JobState::kQueued);
  EXPECT_EQ(again->spec.params.Encode(), DefaultParams("iamls")->Encode());
}

// A rolling update mixes builds: a job stored by a server of a newer spec format is claimed only
// by servers of that format or a newer one; the jobs of older formats are everyone's.
TEST_P(JobStoreContract, JobsAreClaimedOnlyByServersOfTheirSpecFormatOrNewer) {
  SpecTables newer = RegistrySpecTables(), oldest = RegistrySpecTables();
  newer.format = kSpecFormat + 1;
  oldest.format = 0;  // Stores before formats were kept.
  std::shared_ptr<JobStore> new_server = Reopen(newer), old_server = Reopen(oldest);
  ASSERT_NE(new_server, nullptr);
  ASSERT_NE(old_server, nullptr);
  ASSERT_TRUE(new_server->Insert(Queued("newer", 100)).ok());
  ASSERT_TRUE(old_server->Insert(Queued("oldest", 200)).ok());
  ASSERT_TRUE(first_->Insert(Queued("this", 300)).ok());

  // This build passes over the newer job, though it is the oldest, and takes the others.
  std::vector<std::string> claimed;
  for (;;) {
    auto job = first_->Claim("this-build", std::chrono::seconds(30));
    ASSERT_TRUE(job.ok()) << job.status();
    if (!job->has_value()) break;
    claimed.push_back((*job)->id);
  }
  EXPECT_EQ(claimed, (std::vector<std::string>{"oldest", "this"}));
  // It sees the newer job as stored, even where it cannot read its spec: not failed.
  std::vector<std::string> asked;
  auto seen = [&] {
    std::shared_ptr<JobStore> reader = Reopen(WithoutMethods(&asked));
    return reader != nullptr ? reader->Get("newer") : absl::UnavailableError("cannot reopen the store");
  }();
  EXPECT_EQ(asked, std::vector<std::string>{"iamls"});
  ASSERT_TRUE(seen.ok()) << seen.status();
  EXPECT_EQ(seen->state, JobState::kQueued) << seen->error;
  EXPECT_EQ(seen->spec_format, kSpecFormat + 1);

  auto taken = new_server->Claim("newer-build", std::chrono::seconds(30));
  ASSERT_TRUE(taken.ok()) << taken.status();
  ASSERT_TRUE(taken->has_value());
  EXPECT_EQ((*taken)->id, "newer");
  EXPECT_EQ((*taken)->spec_format, kSpecFormat + 1);
}

TEST_P(JobStoreContract, TheFirstValueAgreedOnIsEveryonesAfterIt) {
  auto first = first_->Agree("colour", "red");
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(*first, "red");
  auto later = second_->Agree("colour", "blue");
  ASSERT_TRUE(later.ok()) << later.status();
  EXPECT_EQ(*later, "red");
  // Servers starting at once: one of them decides, and all of them hear the same value.
  std::vector<std::future<absl::StatusOr<std::string>>> racing;
  for (int i = 0; i < 8; ++i) {
    JobStore& store = i % 2 == 0 ? *first_ : *second_;
    racing.push_back(std::async(std::launch::async, [&store, i] { return store.Agree("race", std::to_string(i)); }));
  }
  std::set<std::string> heard;
  for (auto& f : racing) {
    auto value = f.get();
    ASSERT_TRUE(value.ok()) << value.status();
    heard.insert(*value);
  }
  ASSERT_EQ(heard.size(), 1u);
  EXPECT_LT(std::stoi(*heard.begin()), 8);
}

TEST_P(JobStoreContract, ClaimsTakeTheOldestOnceAndOnlyTheHolderWrites) {
  for (int i = 3; i >= 1; --i) ASSERT_TRUE(first_->Insert(Queued(core::StrCat("c", i), i)).ok());
  auto a = first_->Claim("server-a", milliseconds(60'000));
  auto b = second_->Claim("server-b", milliseconds(60'000));
  ASSERT_TRUE(a.ok() && a->has_value() && b.ok() && b->has_value());
  EXPECT_EQ((*a)->id, "c1");
  EXPECT_EQ((*b)->id, "c2");
  EXPECT_EQ((*a)->state, JobState::kRunning);
  EXPECT_EQ((*a)->stage, "starting");
  EXPECT_EQ((*a)->attempts, 1);
  EXPECT_EQ((*a)->runner, "server-a");

  JobRecord stolen = **a;
  stolen.runner = "server-b";
  stolen.stage = "not mine";
  EXPECT_EQ(second_->WriteHeld(stolen).status().code(), absl::StatusCode::kAborted);
  JobRecord progress = **a;
  progress.stage = "fitting";
  progress.progress = 0.5;
  auto seq = first_->WriteHeld(progress);
  ASSERT_TRUE(seq.ok()) << seq.status();
  EXPECT_GT(*seq, (*a)->seq);
  auto seen = second_->Get("c1");
  EXPECT_EQ(seen->stage, "fitting");
  EXPECT_EQ(seen->progress, 0.5);

  progress.state = JobState::kSucceeded;
  ASSERT_TRUE(first_->WriteHeld(progress).ok());
  EXPECT_EQ(first_->WriteHeld(progress).status().code(), absl::StatusCode::kAborted);  // Not running any more.
  auto c = first_->Claim("server-a", milliseconds(60'000));
  ASSERT_TRUE(c.ok() && c->has_value());
  EXPECT_EQ((*c)->id, "c3");
  auto none = second_->Claim("server-b", milliseconds(60'000));
  ASSERT_TRUE(none.ok());
  EXPECT_FALSE(none->has_value());
}

TEST_P(JobStoreContract, ConcurrentClaimsTakeEveryJobExactlyOnce) {
  constexpr int kJobs = 60;
  for (int i = 0; i < kJobs; ++i) ASSERT_TRUE(first_->Insert(Queued(core::StrCat("j", i), 1000 + i)).ok());
  std::mutex mutex;
  std::multiset<std::string> taken;
  std::vector<std::thread> servers;
  for (int t = 0; t < 4; ++t) {
    servers.emplace_back([&, t] {
      JobStore& store = t % 2 == 0 ? *first_ : *second_;
      const std::string runner = core::StrCat("server-", t);
      for (;;) {
        auto claimed = store.Claim(runner, milliseconds(60'000));
        if (!claimed.ok() || !claimed->has_value()) return;
        std::lock_guard lock(mutex);
        taken.insert((*claimed)->id);
      }
    });
  }
  for (auto& t : servers) t.join();
  EXPECT_EQ(taken.size(), static_cast<size_t>(kJobs));
  EXPECT_EQ(std::set<std::string>(taken.begin(), taken.end()).size(), static_cast<size_t>(kJobs));
}

TEST_P(JobStoreContract, LapsedLeasesAreRecoveredAndTheirRunnerLosesItsSay) {
  ASSERT_TRUE(first_->Insert(Queued("l1", 1)).ok());
  ASSERT_TRUE(first_->Insert(Queued("l2", 2)).ok());
  auto dead = first_->Claim("dead-server", milliseconds(0));  // Lapsed at once.
  auto alive = second_->Claim("live-server", milliseconds(60'000));
  ASSERT_TRUE(dead.ok() && dead->has_value() && alive.ok() && alive->has_value());
  // Only the jobs named, and only those the runner holds.
  auto renewed = second_->Renew("live-server", {"l1", "l2", "none"}, milliseconds(60'000));
  ASSERT_TRUE(renewed.ok());
  ASSERT_EQ(renewed->size(), 1u);
  EXPECT_EQ(renewed->front().first, "l2");

  std::vector<std::string> handed;
  auto recovered = second_->RecoverLapsed(false, [&](JobRecord& r) {
    handed.push_back(r.id);
    r.state = JobState::kQueued;
    r.stage.clear();
  });
  ASSERT_TRUE(recovered.ok()) << recovered.status();
  EXPECT_EQ(handed, std::vector<std::string>{"l1"});
  ASSERT_EQ(recovered->size(), 1u);
  EXPECT_EQ(first_->Get("l1")->state, JobState::kQueued);
  EXPECT_EQ(first_->Get("l2")->state, JobState::kRunning);
  JobRecord late = **dead;
  late.state = JobState::kSucceeded;
  EXPECT_EQ(first_->WriteHeld(late).status().code(), absl::StatusCode::kAborted);

  // The job goes to the next claimant with one more attempt.
  auto again = second_->Claim("live-server", milliseconds(60'000));
  ASSERT_TRUE(again.ok() && again->has_value());
  EXPECT_EQ((*again)->id, "l1");
  EXPECT_EQ((*again)->attempts, 2);
  // A store of one server recovers every running job when asked to (it just started).
  auto all = first_->RecoverLapsed(true, [](JobRecord& r) { r.state = JobState::kQueued; });
  ASSERT_TRUE(all.ok());
  EXPECT_EQ(all->size(), 2u);
}

// The child jobs' format of this build's tiles, as the servers claim them.
const int kTiles = TileChildFormat(pu::kTileFormat);

JobRecord Child(const std::string& parent, int64_t index, int64_t created_ms, int format = kTiles) {
  JobRecord r;
  r.id = core::StrCat(parent, "-t", index);
  r.spec.method = kTileMethod;
  r.created_ms = r.updated_ms = created_ms;
  r.parent = parent;
  r.child_index = index;
  r.spec_format = format;
  return r;
}

std::vector<JobRecord> ChildrenIn(JobStore& store, const std::string& parent) {
  std::vector<JobRecord> out;
  auto all = store.ChangesSince(0);
  if (!all.ok()) return out;
  for (JobRecord& r : all->changed) {
    if (r.parent == parent) out.push_back(std::move(r));
  }
  return out;
}

// Children of a running job are claimed before any other job, in order, and only by servers of
// their format (a server of a build before child jobs, which asks for none, never takes one);
// children of a job that does not run wait. Removing the parent removes its children.
TEST_P(JobStoreContract, ChildJobsOfARunningJobComeFirstAndOnlyToServersOfTheirFormat) {
  ASSERT_TRUE(first_->Insert(Queued("p1", 1)).ok());
  ASSERT_TRUE(first_->Insert(Queued("p2", 2)).ok());
  ASSERT_TRUE(first_->Insert(Queued("p3", 3)).ok());
  ASSERT_TRUE(first_->Insert(Child("p2", 0, 2)).ok());  // Its parent is queued: it waits.
  auto p1 = first_->Claim("coordinator", milliseconds(60'000), {kTiles, ""});
  ASSERT_TRUE(p1.ok() && p1->has_value()) << p1.status();
  ASSERT_EQ((*p1)->id, "p1");
  for (int64_t t = 0; t < 2; ++t) ASSERT_TRUE(first_->Insert(Child("p1", t, 1)).ok());
  auto stored = second_->Get("p1-t1");
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_EQ(stored->parent, "p1");
  EXPECT_EQ(stored->child_index, 1);
  EXPECT_EQ(stored->spec_format, kTiles) << "a child's format was replaced by the store's";
  EXPECT_EQ(stored->state, JobState::kQueued) << "a child's spec is read as a job's";

  auto other = second_->Claim("other-build", milliseconds(60'000), {kTiles + 1, "p1"});
  ASSERT_TRUE(other.ok()) << other.status();
  EXPECT_FALSE(other->has_value()) << "a child of another format was claimed";
  auto old = second_->Claim("old-build", milliseconds(60'000));  // Asks for no children.
  ASSERT_TRUE(old.ok() && old->has_value()) << old.status();
  EXPECT_EQ((*old)->id, "p2");
  auto own = first_->Claim("coordinator", milliseconds(60'000), {kTiles, "p2"});
  ASSERT_TRUE(own.ok() && own->has_value()) << own.status();
  EXPECT_EQ((*own)->id, "p2-t0") << "a claim of one job's children took another's";
  for (const char* expected : {"p1-t0", "p1-t1"}) {
    auto helper = second_->Claim("helper", milliseconds(60'000), {kTiles, ""});
    ASSERT_TRUE(helper.ok() && helper->has_value()) << helper.status();
    EXPECT_EQ((*helper)->id, expected) << "children before the queued job p3, in order";
  }
  auto next = second_->Claim("helper", milliseconds(60'000), {kTiles, ""});
  ASSERT_TRUE(next.ok() && next->has_value());
  EXPECT_EQ((*next)->id, "p3");

  // p1 ends while a child still runs: removing p1 removes both, and the removals are reported.
  JobRecord done = **p1;
  done.state = JobState::kSucceeded;
  ASSERT_TRUE(first_->WriteHeld(done).ok());
  auto before = second_->ChangesSince(0);
  ASSERT_TRUE(before.ok());
  ASSERT_TRUE(second_->Remove("p1").ok());
  EXPECT_EQ(first_->Get("p1-t1").status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(ChildrenIn(*first_, "p1").empty());
  auto after = first_->ChangesSince(before->seq);
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(std::set<std::string>(after->removed.begin(), after->removed.end()),
            std::set<std::string>({"p1", "p1-t0", "p1-t1"}));
}

// The tile jobs of a build as tests drive them: this store's records, and `runner` making a
// queued child of the build here when asked (a claim, RunTileJob, the final write).
TileJobs StoreTileJobs(JobStore& store, BlobStore& blobs, const std::string& runner) {
  TileJobs jobs;
  jobs.get = [&store](const std::string& id) { return store.Get(id); };
  jobs.children = [&store](const std::string& parent) { return ChildrenIn(store, parent); };
  jobs.any_queued = [&store](const std::string& parent) {
    const std::vector<JobRecord> children = ChildrenIn(store, parent);
    return std::any_of(children.begin(), children.end(),
                       [](const JobRecord& c) { return c.state == JobState::kQueued; });
  };
  jobs.run_one = [&store, &blobs, runner](const std::string& parent) -> absl::StatusOr<bool> {
    auto claimed = store.Claim(runner, milliseconds(60'000), {kTiles, parent});
    if (!claimed.ok()) return claimed.status();
    if (!claimed->has_value()) return false;
    JobRecord child = **claimed;
    core::LocalJobContext ctx;
    const absl::Status made = RunTileJob(blobs, child, ctx, [] { return true; });
    child.state = made.ok() ? JobState::kSucceeded : JobState::kFailed;
    child.error = std::string(made.message());
    auto written = store.WriteHeld(child);
    if (!written.ok()) return written.status();
    return true;
  };
  jobs.wait = [&store](milliseconds timeout) { store.WaitForOthers(std::min(timeout, milliseconds(50))); };
  jobs.wait_limit = milliseconds(50);
  return jobs;
}

// A tile whose servers stopped while making it (each claim's lease lapsed: out of memory, a
// crash) is not run once more past max_attempts: its child job fails, and the build's server gets
// that reason, naming the tile, in place of its part; a later attempt of the build, under the same
// plan, fails the same way at once.
TEST_P(JobStoreContract, ATileThatStopsItsServerEveryTimeFailsItsBuildNamingIt) {
  ASSERT_TRUE(first_->Insert(Queued("t1", 1)).ok());
  auto job = first_->Claim("coordinator", milliseconds(60'000), {kTiles, ""});
  ASSERT_TRUE(job.ok() && job->has_value()) << job.status();
  const std::filesystem::path blob_dir = testing::FreshTestDir("lsqsurf-tile-blobs");
  auto blobs = LocalDirBlobStore::Open(blob_dir.string());
  ASSERT_TRUE(blobs.ok()) << blobs.status();
  TileJobs jobs = StoreTileJobs(*first_, **blobs, "coordinator");
  jobs.run_one = [](const std::string&) -> absl::StatusOr<bool> { return false; };  // Helpers make it.
  StoreTileExchange exchange(*first_, **blobs, **job, jobs);
  core::LocalJobContext ctx;
  auto planned = pu::PlannedCloud::Plan(pu::CloudSource(testing::SphereCloud(2'000)), {}, {}, {}, ctx);
  ASSERT_TRUE(planned.ok()) << planned.status();
  const std::string plan = pu::EncodeTilePlan((*planned)->plan());  // Nobody makes the tile here.
  ASSERT_TRUE(exchange.Publish(plan, 1, [](int64_t) -> absl::StatusOr<std::string> { return "points"; }).ok());
  for (const char* runner : {"crashed-a", "crashed-b"}) {
    auto claimed = second_->Claim(runner, milliseconds(0), {kTiles, ""});  // Lapsed at once, as if it died.
    ASSERT_TRUE(claimed.ok() && claimed->has_value()) << runner;
    EXPECT_EQ((*claimed)->parent, "t1");
    auto recovered = second_->RecoverLapsed(false, [](JobRecord& r) { RecoverStoppedRun(r, 2); });
    ASSERT_TRUE(recovered.ok()) << recovered.status();
    ASSERT_EQ(recovered->size(), 1u) << "only the tile's lease lapsed";
  }
  auto part = exchange.Part(0, ctx);
  EXPECT_EQ(part.status().code(), absl::StatusCode::kInternal);
  EXPECT_TRUE(
      absl::StartsWith(part.status().message(), "tile 0: the server making it stopped on each of its 2 attempts"))
      << part.status();
  auto more = second_->Claim("helper", milliseconds(60'000), {kTiles, ""});
  ASSERT_TRUE(more.ok());
  EXPECT_FALSE(more->has_value()) << "the failed tile is still offered";
  JobRecord next_attempt = **job;
  ++next_attempt.attempts;
  StoreTileExchange again(*first_, **blobs, next_attempt, jobs);
  const absl::Status republished =
      again.Publish(plan, 1, [](int64_t) -> absl::StatusOr<std::string> { return "points"; });
  EXPECT_TRUE(absl::StartsWith(republished.message(), "tile 0: the server making it")) << republished;
  again.Clear();
  EXPECT_TRUE(ChildrenIn(*first_, "t1").empty()) << "the build's tile jobs stay behind";
  std::filesystem::remove_all(blob_dir);
}

// A tiled build whose server stopped halfway (no Clear: a kill) is run again by the job's next
// attempt: the plan is the same but for its timings, so the tiles the first attempt's children
// made are used again instead of being made anew, and the surface is the one a single process
// makes. A server whose blob store is not the one the build published to says so.
TEST_P(JobStoreContract, AResumedTiledBuildReusesTheTilesOfItsEarlierAttempt) {
  ASSERT_TRUE(first_->Insert(Queued("t1", 1)).ok());
  auto job = first_->Claim("r1/coordinator", milliseconds(60'000), {kTiles, ""});
  ASSERT_TRUE(job.ok() && job->has_value()) << job.status();
  const std::filesystem::path blob_dir = testing::FreshTestDir("lsqsurf-resumed-tiles");
  auto blobs = LocalDirBlobStore::Open(blob_dir.string());
  ASSERT_TRUE(blobs.ok()) << blobs.status();
  const core::PointCloud cloud = testing::SphereCloud(20'000);
  const pu::PuTileParams tiles{.tile_points = 4'000, .support_cap = 16};
  core::LocalJobContext ctx;
  {
    auto planned = pu::PlannedCloud::Plan(pu::CloudSource(cloud), {}, {}, tiles, ctx);
    ASSERT_TRUE(planned.ok()) << planned.status();
    const pu::TilePlan& plan = (*planned)->plan();
    StoreTileExchange first_attempt(*first_, **blobs, **job, StoreTileJobs(*first_, **blobs, "r1/coordinator"));
    ASSERT_TRUE(first_attempt
                    .Publish(pu::EncodeTilePlan(plan), static_cast<int64_t>(plan.tiles.size()),
                             [&](int64_t t) -> absl::StatusOr<std::string> {
                               auto points = (*planned)->TilePoints(static_cast<size_t>(t));
                               if (!points.ok()) return points.status();
                               return pu::EncodeTilePoints(*points);
                             })
                    .ok());
    const std::filesystem::path other_dir = testing::FreshTestDir("lsqsurf-unshared-blobs");
    auto unshared = LocalDirBlobStore::Open(other_dir.string());  // Holds none of the build's blobs.
    ASSERT_TRUE(unshared.ok()) << unshared.status();
    const absl::Status unreadable = RunTileJob(**unshared, ChildrenIn(*first_, "t1").front(), ctx, [] { return true; });
    EXPECT_EQ(unreadable.code(), absl::StatusCode::kFailedPrecondition) << unreadable;
    EXPECT_TRUE(absl::StrContains(unreadable.message(), "blob store")) << unreadable;
    std::filesystem::remove_all(other_dir);
    const TileJobs helper = StoreTileJobs(*second_, **blobs, "r2/helper");
    for (int made = 0; made < 3; ++made) {
      auto ran = helper.run_one("t1");
      ASSERT_TRUE(ran.ok() && *ran) << ran.status();
    }
  }  // The first attempt's server is gone, its tile jobs and blobs left behind.
  JobRecord resumed_job = **job;
  ++resumed_job.attempts;
  StoreTileExchange second_attempt(*first_, **blobs, resumed_job, StoreTileJobs(*first_, **blobs, "r1/coordinator"));
  pu::MeshSink resumed;
  auto built = ReconstructTiledShared(pu::CloudSource(cloud), {}, {}, tiles, resumed, ctx, {"", &second_attempt});
  ASSERT_TRUE(built.ok()) << built.status();
  EXPECT_EQ(second_attempt.Reused(), 3);
  EXPECT_EQ(second_attempt.Servers(), 1) << "the reused parts count for no server";
  EXPECT_FALSE((*blobs)->Exists("t1", "tile-plan")) << "the build's blobs stay behind";
  EXPECT_TRUE(ChildrenIn(*first_, "t1").empty()) << "the build's tile jobs stay behind";
  pu::MeshSink alone;
  ASSERT_TRUE(pu::ReconstructTiled(pu::CloudSource(cloud), {}, {}, tiles, alone, ctx).ok());
  ASSERT_EQ(resumed.mesh().faces.size(), alone.mesh().faces.size());
  auto sorted = [](std::vector<core::Vec3f> v) {
    std::sort(v.begin(), v.end(), [](const core::Vec3f& a, const core::Vec3f& b) {
      return std::lexicographical_compare(a.data(), a.data() + 3, b.data(), b.data() + 3);
    });
    return v;
  };
  EXPECT_TRUE(sorted(resumed.mesh().vertices) == sorted(alone.mesh().vertices));
  std::filesystem::remove_all(blob_dir);
}

TEST_P(JobStoreContract, CancelStopsQueuedJobsAndFlagsRunningOnes) {
  ASSERT_TRUE(first_->Insert(Queued("q1", 1)).ok());
  ASSERT_TRUE(first_->Insert(Queued("q2", 2)).ok());
  auto running = first_->Claim("server-a", milliseconds(60'000));
  ASSERT_TRUE(running.ok() && running->has_value());

  auto queued = second_->Cancel("q2", "cancelled by request before it started");
  ASSERT_TRUE(queued.ok()) << queued.status();
  EXPECT_EQ(queued->state, JobState::kCancelled);
  EXPECT_EQ(queued->error, "cancelled by request before it started");

  auto flagged = second_->Cancel("q1", "unused");
  ASSERT_TRUE(flagged.ok());
  EXPECT_EQ(flagged->state, JobState::kRunning);
  EXPECT_TRUE(flagged->cancel_requested);
  // The runner's own writes do not lower the flag; its renewal tells it.
  JobRecord progress = **running;
  progress.stage = "fitting";
  ASSERT_TRUE(first_->WriteHeld(progress).ok());
  auto renewed = first_->Renew("server-a", {"q1"}, milliseconds(60'000));
  ASSERT_TRUE(renewed.ok());
  ASSERT_EQ(renewed->size(), 1u);
  EXPECT_TRUE(renewed->front().second);

  EXPECT_EQ(second_->Cancel("q2", "again").status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(second_->Cancel("none", "x").status().code(), absl::StatusCode::kNotFound);
}

TEST_P(JobStoreContract, OnlyFinishedJobsAreRemovedAndRemovalsAreReported) {
  ASSERT_TRUE(first_->Insert(Queued("r1", 1)).ok());
  EXPECT_EQ(second_->Remove("r1").code(), absl::StatusCode::kFailedPrecondition);
  auto before = second_->ChangesSince(0);
  ASSERT_TRUE(before.ok());
  ASSERT_EQ(before->changed.size(), 1u);
  ASSERT_TRUE(first_->Cancel("r1", "stop").ok());
  ASSERT_TRUE(second_->Remove("r1").ok());
  EXPECT_EQ(second_->Remove("r1").code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(first_->Get("r1").status().code(), absl::StatusCode::kNotFound);
  auto after = first_->ChangesSince(before->seq);
  ASSERT_TRUE(after.ok());
  EXPECT_TRUE(after->changed.empty());  // Cancelled, then gone: only the removal is left to tell.
  EXPECT_EQ(after->removed, std::vector<std::string>{"r1"});
  EXPECT_GT(after->seq, before->seq);
}

TEST_P(JobStoreContract, ChangesArriveInOrderAndOnlyOnce) {
  ASSERT_TRUE(first_->Insert(Queued("o1", 1)).ok());
  auto start = second_->ChangesSince(0);
  ASSERT_TRUE(start.ok());
  EXPECT_EQ(start->changed.size(), 1u);
  auto quiet = second_->ChangesSince(start->seq);
  ASSERT_TRUE(quiet.ok());
  EXPECT_TRUE(quiet->changed.empty());
  EXPECT_EQ(quiet->seq, start->seq);

  ASSERT_TRUE(first_->Insert(Queued("o2", 2)).ok());
  auto claimed = first_->Claim("server-a", milliseconds(60'000));
  ASSERT_TRUE(claimed.ok() && claimed->has_value());
  // A renewal alone is not a change.
  ASSERT_TRUE(first_->Renew("server-a", {"o1"}, milliseconds(90'000)).ok());
  auto next = second_->ChangesSince(start->seq);
  ASSERT_TRUE(next.ok());
  ASSERT_EQ(next->changed.size(), 2u);
  EXPECT_LT(next->changed[0].seq, next->changed[1].seq);
  EXPECT_EQ(next->changed[0].id, "o2");
  EXPECT_EQ(next->changed[1].id, "o1");
  EXPECT_EQ(next->changed[1].state, JobState::kRunning);
  EXPECT_EQ(next->seq, next->changed[1].seq);
}

TEST_P(JobStoreContract, AnotherServersWriteWakesAWaiter) {
  if (!first_->shared()) GTEST_SKIP() << "a store of one server has nobody else to wait for";
  // A waiter for up to a minute returns once the other store writes: its notification arrives.
  auto waited = std::async(std::launch::async, [&] {
    const auto start = std::chrono::steady_clock::now();
    second_->WaitForOthers(milliseconds(60'000));
    return std::chrono::steady_clock::now() - start;
  });
  ASSERT_TRUE(first_->Insert(Queued("w1", 1)).ok());
  EXPECT_LT(waited.get(), std::chrono::seconds(30));
}

#if LSQSURF_WITH_POSTGRESQL
TEST(PostgresUrl, PasswordsNeverReachMessages) {
  EXPECT_EQ(pg::Redacted("postgresql://lsqsurf:s3cret@db:5432/jobs"), "postgresql://lsqsurf:***@db:5432/jobs");
  EXPECT_EQ(pg::Redacted("postgresql://lsqsurf@db/jobs"), "postgresql://lsqsurf@db/jobs");
  EXPECT_EQ(pg::Redacted("host=db password = 's3 cret' user=x"), "host=db password = *** user=x");
  EXPECT_EQ(pg::Redacted("host=db password=s3cret"), "host=db password=***");
  auto refused =
      PostgresJobStore::Open("postgresql://lsqsurf:s3cret@127.0.0.1:1/jobs?connect_timeout=2", RegistrySpecTables());
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(std::string(refused.status().message()).find("s3cret"), std::string::npos) << refused.status();
}
#endif

INSTANTIATE_TEST_SUITE_P(Stores, JobStoreContract, ::testing::Values("sqlite", "postgresql"),
                         [](const ::testing::TestParamInfo<std::string>& param) { return param.param; });

}  // namespace
}  // namespace lsqsurf::jobs
