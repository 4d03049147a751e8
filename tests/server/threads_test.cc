// The server's shared state under many threads, without gRPC in the way: the character store (memory LRU over
// the cache directory) and the solver pool. CI runs these under ThreadSanitizer, fully instrumented (Debian's
// gRPC is not, so TSan cannot judge the gRPC-driven tests; see tests/tsan.supp).
#include <gtest/gtest.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <future>
#include <mutex>
#include <set>
#include <thread>

#include "character_store.h"
#include "solver_pool.h"
#include "springblend/mesh.h"
#include "test_util.h"

namespace springblend::server {
namespace {

// A tetrahedron and a target: cheap to build, so eviction and rebuilds happen often.
CharacterData Tetrahedron(double bending) {
  const TriangleMesh rest = LoadMeshFromText(
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n", "obj", "tetrahedron");
  CharacterData d;
  d.name = "tet";
  d.target_names = {"stretch"};
  d.faces = rest.faces;
  Points target = rest.vertices;
  target(3, 2) = 1.5;
  d.shapes = {rest.vertices, target};
  d.options.bending_stiffness = bending;
  return d;
}

// A build option that changes the solved frames (no target paths: other starts, so possibly other equilibria)
// is part of the id and of the cache file: a replica that rebuilds the character from disk builds the same rig.
TEST(StoreFile, TheIdAndTheCacheFileKeepBuildOptionsThatChangeFrames) {
  CharacterData with = Tetrahedron(1.0), without = Tetrahedron(1.0);
  without.options.target_paths = false;
  EXPECT_NE(ContentId(with), ContentId(without));
  EXPECT_FALSE(Deserialize(Serialize(without)).options.target_paths);
  EXPECT_TRUE(Deserialize(Serialize(with)).options.target_paths);
  // The held rim too, with and without paths; a character without either keeps the bytes it always had.
  CharacterData rim = Tetrahedron(1.0), rim_without = without;
  rim.options.hold_outer_rim = rim_without.options.hold_outer_rim = true;
  EXPECT_EQ(std::set<std::string>({ContentId(with), ContentId(without), ContentId(rim), ContentId(rim_without)}).size(),
            4u);
  for (const CharacterData* d : {&rim, &rim_without}) {
    const CharacterData back = Deserialize(Serialize(*d));
    EXPECT_TRUE(back.options.hold_outer_rim);
    EXPECT_EQ(back.options.target_paths, d->options.target_paths);
    EXPECT_EQ(Serialize(back), Serialize(*d));
  }
  EXPECT_FALSE(Deserialize(Serialize(without)).options.hold_outer_rim);
  EXPECT_EQ(Serialize(with).find("SBOPT001"), std::string::npos);
  // The paths' density, with and without the held rim: another id, kept by the cache file.
  CharacterData dense = Tetrahedron(1.0), dense_rim = rim;
  dense.options.path_intervals = dense_rim.options.path_intervals = 64;
  dense.options.path_max_samples = dense_rim.options.path_max_samples = 128;
  EXPECT_EQ(std::set<std::string>({ContentId(with), ContentId(rim), ContentId(dense), ContentId(dense_rim)}).size(), 4u);
  for (const CharacterData* d : {&dense, &dense_rim}) {
    const CharacterData back = Deserialize(Serialize(*d));
    EXPECT_EQ(back.options.path_intervals, 64);
    EXPECT_EQ(back.options.path_max_samples, 128);
    EXPECT_EQ(back.options.hold_outer_rim, d->options.hold_outer_rim);
    EXPECT_TRUE(back.options.target_paths);
    EXPECT_EQ(Serialize(back), Serialize(*d));
  }
  // A file whose density is out of range is refused, naming the option.
  CharacterData wild = dense;
  wild.options.path_intervals = 100000;
  const Error refused = testing::CatchError([&] { Deserialize(Serialize(wild)); });
  EXPECT_EQ(refused.code(), ErrorCode::kInvalidInput);
  EXPECT_NE(std::string(refused.what()).find("path_intervals"), std::string::npos) << refused.what();
  testing::TempDir dir;
  std::string id;
  {
    CharacterStore store({dir.path().string(), 4LL << 30});
    id = store.Put(without).first->id;
  }
  CharacterStore restarted({dir.path().string(), 4LL << 30});
  const auto entry = restarted.Get(id);
  ASSERT_TRUE(entry);
  EXPECT_FALSE(entry->rig->options().target_paths);
  EXPECT_EQ(entry->rig->summary().path_samples, 0);
}

TEST(StoreThreads, PutGetListDeleteFromManyThreadsUnderATinyBudget) {
  testing::TempDir dir;
  CharacterStore store({dir.path().string(), 1});  // 1 byte: every insertion evicts the others
  std::vector<CharacterData> characters;
  for (int i = 0; i < 3; ++i) characters.push_back(Tetrahedron(1.0 + i));
  std::vector<std::string> ids;
  for (const auto& c : characters) ids.push_back(ContentId(c));
  std::atomic<int> failures{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      for (int round = 0; round < 8; ++round) {
        const size_t i = static_cast<size_t>(t + round) % characters.size();
        try {
          const auto [entry, known] = store.Put(characters[i]);
          if (entry->id != ids[i]) ++failures;
          const auto again = store.Get(ids[(i + 1) % ids.size()]);
          if (again && again->rig->num_targets() != 1) ++failures;
          store.List();
          store.stats();
          if (round % 3 == 2) store.Delete(ids[i]);
        } catch (const std::exception& e) {
          ++failures;
          ADD_FAILURE() << e.what();
        }
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(failures, 0);
  for (size_t i = 0; i < characters.size(); ++i) {
    store.Put(characters[i]);
    ASSERT_NE(store.Get(ids[i]), nullptr);
  }
  EXPECT_GT(store.stats().evictions, 0);
}

// A replica starting on a shared cache directory removes what killed writers left, while another replica keeps
// writing there: every file a live writer holds must survive (it locks its temporary until the rename).
TEST(StoreThreads, AStartUpCleanupBesideALiveWriterRemovesOnlyDeadWritersFiles) {
  namespace fs = std::filesystem;
  testing::TempDir dir;
  const std::string dead = (dir.path() / (std::string(64, 'c') + ".sbchar.tmp.77.0123abcd")).string();
  std::ofstream(dead) << "half a character";
  CharacterStore writer({dir.path().string(), 1LL << 30});
  CharacterStore starting({dir.path().string(), 1LL << 30});
  std::atomic<bool> done{false};
  std::atomic<int> removed{0}, in_use{0};
  std::thread cleaner([&] {
    while (!done) {
      const CharacterStore::Cleanup c = starting.RemoveStaleTemporaries();
      removed += c.removed;
      in_use += c.in_use;
    }
  });
  std::vector<std::string> ids;
  for (int i = 0; i < 40; ++i) {
    CharacterData character = Tetrahedron(1.0 + 0.01 * i);
    character.options.interior = false;  // no TetGen: many quick writes
    ids.push_back(writer.Put(character).first->id);
  }
  done = true;
  cleaner.join();
  // The dead writer's file, and possibly a live writer's just-created one that the cleaner locked or removed in
  // the moment before its writer locked it: that writer then starts over under another name (WriteFile), so
  // nothing it wrote is lost, as the checks below show.
  EXPECT_GE(removed, 1) << "the dead writer's file";
  EXPECT_FALSE(fs::exists(dead));
  std::cout << "the cleaner met " << in_use << " temporaries in use and kept them\n";
  for (const auto& id : ids) EXPECT_TRUE(fs::exists(dir.path() / (id + ".sbchar"))) << id;
  for (const auto& file : fs::directory_iterator(dir.path())) {
    EXPECT_EQ(file.path().extension(), ".sbchar") << file.path() << " was left behind";
  }
}

TEST(PoolThreads, EveryAcceptedJobRunsOnceFromManySubmitters) {
  std::atomic<int> accepted{0}, ran{0};
  std::mutex mutex;
  std::set<int> seen;
  {
    SolverPool pool(3, 8);
    std::vector<std::thread> submitters;
    for (int s = 0; s < 4; ++s) {
      submitters.emplace_back([&, s] {
        for (int j = 0; j < 200; ++j) {
          const int key = s * 1000 + j;
          if (pool.TrySubmit([&, key] {
                ++ran;
                std::lock_guard lock(mutex);
                seen.insert(key);
              })) {
            ++accepted;
          }
          pool.queue_depth();
          pool.busy();
        }
      });
    }
    for (auto& t : submitters) t.join();
  }  // the destructor finishes queued jobs
  EXPECT_EQ(ran, accepted);
  EXPECT_EQ(static_cast<int>(seen.size()), accepted.load());
  EXPECT_GT(accepted, 0);
}

// A slider session's jobs run before a bake's queued frames, and each kind keeps its order.
TEST(PoolThreads, InteractiveJobsRunBeforeQueuedOnesInTheirOrder) {
  std::mutex mutex;
  std::vector<std::string> order;
  std::promise<void> release;
  std::shared_future<void> released = release.get_future().share();
  {
    SolverPool pool(1, 8);
    std::promise<void> started;
    ASSERT_TRUE(pool.TrySubmit([&] {
      started.set_value();
      released.wait();
    }));
    started.get_future().wait();  // the one thread is busy: what follows queues
    const auto record = [&](std::string name) {
      return [&, name] {
        std::lock_guard lock(mutex);
        order.push_back(name);
      };
    };
    ASSERT_TRUE(pool.TrySubmit(record("bake 1")));
    ASSERT_TRUE(pool.SubmitContinuation(record("bake 2")));
    ASSERT_TRUE(pool.TrySubmit(record("slider 1"), true));
    ASSERT_TRUE(pool.SubmitContinuation(record("slider 2"), true));
    EXPECT_EQ(pool.queue_depth(), 4);
    release.set_value();
  }
  EXPECT_EQ(order, (std::vector<std::string>{"slider 1", "slider 2", "bake 1", "bake 2"}));
}

}  // namespace
}  // namespace springblend::server
