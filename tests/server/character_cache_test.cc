// The cache directory keeps what is costly to build (issue 24): a rebuild from a cache file loads the rig's
// target paths instead of solving them, files of older versions (no paths) still load and are upgraded, a
// corrupt paths part is refused like a corrupt file; and builds stop when their caller's stop check says so,
// without failing other callers waiting for the same build. CharacterStore alone, no gRPC.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <openssl/evp.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <future>
#include <sstream>
#include <thread>

#include "character_store.h"
#include "springblend/solve.h"
#include "test_util.h"

namespace springblend::server {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using Clock = std::chrono::steady_clock;

// The rest mesh and targets of a bundled character as an upload's data.
CharacterData Character(const std::string& rest, const std::vector<std::string>& targets) {
  const TriangleMesh mesh = LoadMesh(testing::DataPath(rest));
  CharacterData d;
  d.name = fs::path(rest).stem().string();
  d.faces = mesh.faces;
  d.shapes = {mesh.vertices};
  for (const auto& t : targets) {
    d.target_names.push_back(fs::path(t).stem().string());
    d.shapes.push_back(LoadMesh(testing::DataPath(t)).vertices);
  }
  return d;
}
// About a second to build, most of it the target paths.
CharacterData Cylinder() {
  return Character("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-3.obj"});
}
// About ten seconds to build: time to stop it part way.
CharacterData Cube() {
  return Character("cube/cube.obj", {"cube/poses-1_cube-1.obj", "cube/poses-1_cube-2.obj", "cube/poses-1_cube-3.obj",
                                     "cube/poses-1_cube-4.obj"});
}

std::string Sha256(const std::string& bytes) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_Digest(bytes.data(), bytes.size(), digest, &length, EVP_sha256(), nullptr);
  return std::string(reinterpret_cast<const char*>(digest), length);
}

std::string ReadAll(const fs::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

// What the store logs while it lives (spdlog's default logger, restored after).
class LogCapture {
 public:
  LogCapture() : previous_(spdlog::default_logger()) {
    spdlog::set_default_logger(
        std::make_shared<spdlog::logger>("capture", std::make_shared<spdlog::sinks::ostream_sink_mt>(text_)));
  }
  ~LogCapture() { spdlog::set_default_logger(previous_); }
  std::string text() const { return text_.str(); }

 private:
  std::ostringstream text_;
  std::shared_ptr<spdlog::logger> previous_;
};

// One frame of the rig, as the server would solve it.
Points Solved(const std::shared_ptr<const Rig>& rig) {
  Frame frame;
  frame.weights = {0.7, 0.4};
  Points positions;
  Solver(rig).Solve(frame, &positions);
  return positions;
}

// A restart (a new store on the directory) builds the rig with the paths the first build wrote: nothing solved,
// the same rig, so the same frames.
TEST(CacheFile, ARestartLoadsTheTargetPathsFromTheFile) {
  testing::TempDir dir;
  const CharacterData cylinder = Cylinder();
  std::shared_ptr<const CharacterStore::Entry> first;
  {
    CharacterStore store({dir.path().string()});
    first = store.Put(cylinder).first;
  }
  const RigSummary& built = first->rig->summary();
  EXPECT_FALSE(built.paths_loaded);
  EXPECT_GT(built.path_samples, 0);
  const std::string file = ReadAll(dir.path() / (first->id + ".sbchar"));
  EXPECT_EQ(file.substr(0, 8), "SBCHAR02");
  EXPECT_GT(file.size(), Serialize(cylinder).size() + first->rig->SavePrecomputed().size()) << "both parts";
  // The build left each path in a spool without a name as it was solved, and the file was written from there in
  // pieces: the directory holds the character's file alone.
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir.path()), std::filesystem::directory_iterator()), 1);
  for (const std::string& note : built.notes) EXPECT_THAT(note, ::testing::Not(HasSubstr("held in memory")));

  LogCapture log;
  CharacterStore restarted({dir.path().string()});
  const auto again = restarted.Get(first->id);
  ASSERT_TRUE(again);
  EXPECT_TRUE(again->rig->summary().paths_loaded);
  EXPECT_EQ(again->rig->summary().path_samples, built.path_samples);
  // The samples stay in the file, read as frames need them, from the upload on and after a restart: the
  // character holds their metadata only, and its memory estimate (the store's budget) is smaller by them than a
  // memory-only store's.
  CharacterStore memory_only({});
  const auto held = memory_only.Put(cylinder).first;
  const RigSummary& in_memory = held->rig->summary();
  EXPECT_EQ(in_memory.path_file_bytes, 0);
  EXPECT_EQ(held->rig->SavePrecomputed(), first->rig->SavePrecomputed());
  for (const RigSummary* s : {&built, &again->rig->summary()}) {
    EXPECT_GT(s->path_file_bytes, in_memory.path_bytes * 9 / 10);
    EXPECT_LT(s->path_bytes, in_memory.path_bytes / 10);
  }
  EXPECT_LT(first->bytes, held->bytes);
  EXPECT_EQ(again->bytes, first->bytes);
  EXPECT_EQ(Solved(held->rig), Solved(first->rig));
  EXPECT_EQ(again->rig->SavePrecomputed(), first->rig->SavePrecomputed());
  EXPECT_EQ(Solved(again->rig), Solved(first->rig));
  EXPECT_EQ(restarted.stats().paths_loaded, 1);
  EXPECT_EQ(restarted.stats().upgraded_files, 0);
  EXPECT_THAT(log.text(), HasSubstr("target paths loaded from the file"));
  EXPECT_EQ(ReadAll(dir.path() / (first->id + ".sbchar")), file) << "a file with fitting paths is not rewritten";
  ASSERT_EQ(restarted.List().size(), 1u);
  EXPECT_EQ(restarted.List()[0].name, "cylinder");
}

// A version 1 file (an older server's: magic, SHA-256 of the payload, payload) still loads: the paths are
// solved, the log says so, and the file is rewritten as version 2, from which the next restart loads them.
TEST(CacheFile, AVersionOneFileLoadsAndIsUpgraded) {
  testing::TempDir dir;
  const CharacterData cylinder = Cylinder();
  const std::string id = ContentId(cylinder);
  const fs::path path = dir.path() / (id + ".sbchar");
  const std::string payload = Serialize(cylinder);
  std::ofstream(path, std::ios::binary) << "SBCHAR01" << Sha256(payload) << payload;
  {
    CharacterStore store({dir.path().string()});
    const auto listed = store.List();  // the name from a version 1 header
    ASSERT_EQ(listed.size(), 1u);
    EXPECT_EQ(listed[0].name, "cylinder");
    EXPECT_EQ(listed[0].entry, nullptr);
    LogCapture log;
    const auto entry = store.Get(id);
    ASSERT_TRUE(entry);
    EXPECT_FALSE(entry->rig->summary().paths_loaded);
    EXPECT_GT(entry->rig->summary().path_samples, 0);
    EXPECT_THAT(log.text(), HasSubstr("has no precomputed paths (version 1): rebuilding them"));
    EXPECT_THAT(log.text(), HasSubstr("target paths solved"));
    EXPECT_EQ(store.stats().upgraded_files, 1);
    EXPECT_EQ(store.stats().rebuilds_from_disk, 1);
  }
  const std::string upgraded = ReadAll(path);
  EXPECT_EQ(upgraded.substr(0, 8), "SBCHAR02");
  CharacterStore restarted({dir.path().string()});
  ASSERT_EQ(restarted.List().size(), 1u);
  EXPECT_EQ(restarted.List()[0].name, "cylinder") << "the name from a version 2 header";
  const auto entry = restarted.Get(id);
  ASSERT_TRUE(entry);
  EXPECT_TRUE(entry->rig->summary().paths_loaded);
  EXPECT_EQ(restarted.stats().upgraded_files, 0);
  EXPECT_EQ(ReadAll(path), upgraded);
}

// Paths that do not fit the rig (here: another version's bytes, with a valid checksum) are not used: the paths
// are solved, the log says why, and the file is rewritten with paths that fit.
TEST(CacheFile, PathsThatDoNotFitAreSolvedAndTheFileRewritten) {
  testing::TempDir dir;
  const CharacterData cylinder = Cylinder();
  const std::string id = ContentId(cylinder);
  const fs::path path = dir.path() / (id + ".sbchar");
  const std::string payload = Serialize(cylinder), unfit = "SBPATH99 from a future version";
  const std::uint64_t length = payload.size();
  {
    std::ofstream out(path, std::ios::binary);
    out << "SBCHAR02" << Sha256(payload);
    out.write(reinterpret_cast<const char*>(&length), sizeof(length));
    out << payload << Sha256(unfit) << unfit;
  }
  LogCapture log;
  CharacterStore store({dir.path().string()});
  const auto entry = store.Get(id);
  ASSERT_TRUE(entry);
  EXPECT_FALSE(entry->rig->summary().paths_loaded);
  EXPECT_THAT(log.text(), HasSubstr("the precomputed target paths were not used"));
  EXPECT_EQ(store.stats().upgraded_files, 1);
  CharacterStore restarted({dir.path().string()});
  ASSERT_TRUE(restarted.Get(id));
  EXPECT_EQ(restarted.stats().paths_loaded, 1);
}

// A flipped byte in the paths part fails its checksum: the file is refused, logged and removed, as a corrupt
// character part is; a new upload writes it anew.
TEST(CacheFile, ACorruptPathsPartIsRefusedAndRemoved) {
  testing::TempDir dir;
  const CharacterData cylinder = Cylinder();
  std::string id;
  {
    CharacterStore store({dir.path().string()});
    id = store.Put(cylinder).first->id;
  }
  const fs::path path = dir.path() / (id + ".sbchar");
  const auto size = fs::file_size(path);
  {
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    f.seekg(static_cast<std::streamoff>(size - 10));
    const char c = static_cast<char>(f.get());
    f.seekp(static_cast<std::streamoff>(size - 10));
    f.put(static_cast<char>(c ^ 0x5a));
  }
  LogCapture log;
  CharacterStore restarted({dir.path().string()});
  EXPECT_EQ(restarted.Get(id), nullptr);
  EXPECT_FALSE(fs::exists(path));
  EXPECT_EQ(restarted.stats().corrupt_files, 1);
  EXPECT_THAT(log.text(), HasSubstr("is corrupt"));
  EXPECT_THAT(log.text(), HasSubstr("the precomputed paths' checksum does not match"));
  EXPECT_TRUE(restarted.List().empty());
  // A file cut short anywhere (in the header, the character, the paths' checksum or the paths) too.
  EXPECT_FALSE(restarted.Put(cylinder).second);
  const std::string whole = ReadAll(path);
  const size_t paths_at = 48 + Serialize(cylinder).size();
  for (const size_t cut : {size_t{0}, size_t{7}, size_t{8}, size_t{40}, size_t{47}, size_t{48}, size_t{60}, size_t{79},
                           paths_at, paths_at + 31, paths_at + 32, whole.size() - 1000, whole.size() - 1}) {
    std::ofstream(path, std::ios::binary | std::ios::trunc) << whole.substr(0, cut);
    CharacterStore again({dir.path().string()});
    EXPECT_TRUE(again.List().empty()) << "cut at " << cut;
    EXPECT_FALSE(fs::exists(path)) << "cut at " << cut;
  }
}

// A stop check that turns true while a build runs ends it within a second: Put throws Error(kCancelled), and
// nothing is kept, neither in memory nor in the directory.
TEST(CancelledBuild, StopsWithinASecondAndKeepsNothing) {
  testing::TempDir dir;
  CharacterStore store({dir.path().string()});
  std::atomic<bool> stop{false};
  std::atomic<std::int64_t> stopped_at{0};
  std::thread stopper([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    stopped_at = Clock::now().time_since_epoch().count();
    stop = true;
  });
  const CharacterData cube = Cube();
  const Error error = testing::CatchError([&] { store.Put(cube, [&] { return stop.load(); }); });
  const auto returned = Clock::now();
  stopper.join();
  EXPECT_EQ(error.code(), ErrorCode::kCancelled) << error.what();
  const auto stopped = Clock::time_point(Clock::duration(stopped_at.load()));
  const auto limit = std::chrono::milliseconds(static_cast<int>(1000 * testing::kSlowdown));
  EXPECT_LT(returned - stopped, limit);
  // Its only waiter gone, the build itself stops at its next check.
  while (store.stats().cancelled_builds == 0 && Clock::now() - stopped < 2 * limit) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_LT(Clock::now() - stopped, limit) << "the build went on without a waiter";
  const StoreStats stats = store.stats();
  EXPECT_EQ(stats.characters, 0);
  EXPECT_EQ(stats.cancelled_builds, 1);
  EXPECT_TRUE(fs::is_empty(dir.path())) << "no cache file, no temporary";
  EXPECT_EQ(store.Get(ContentId(cube)), nullptr);
}

// Callers share one build, which goes on while one of them wants it: when the caller who started it stops, a
// second caller who did not stop is not failed, and the one build finishes for it.
TEST(CancelledBuild, AWaiterWhoDidNotStopKeepsTheBuildGoing) {
  testing::TempDir dir;
  CharacterStore store({dir.path().string()});
  const CharacterData cylinder = Cylinder();
  std::atomic<bool> stop{false};
  auto first = std::async(std::launch::async, [&] { return store.Put(cylinder, [&] { return stop.load(); }); });
  while (store.stats().builds == 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  auto second = std::async(std::launch::async, [&] { return store.Put(cylinder); });
  while (store.stats().misses < 2) std::this_thread::sleep_for(std::chrono::milliseconds(1));  // it waits
  stop = true;
  EXPECT_EQ(testing::CatchError([&] { first.get(); }).code(), ErrorCode::kCancelled);
  const auto [entry, known] = second.get();
  ASSERT_TRUE(entry);
  const StoreStats stats = store.stats();
  EXPECT_EQ(stats.builds, 1);
  EXPECT_EQ(stats.cancelled_builds, 0);
  EXPECT_EQ(stats.characters, 1);
  EXPECT_TRUE(fs::exists(dir.path() / (entry->id + ".sbchar")));
}

// The other way round: a waiter who stops stops waiting at once, and the build goes on for its first caller.
TEST(CancelledBuild, AWaiterWhoStopsDoesNotStopTheBuild) {
  testing::TempDir dir;
  CharacterStore store({dir.path().string()});
  const CharacterData cylinder = Cylinder();
  auto first = std::async(std::launch::async, [&] { return store.Put(cylinder); });
  while (store.stats().builds == 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  std::atomic<bool> stop{false};
  auto second = std::async(std::launch::async, [&] { return store.Put(cylinder, [&] { return stop.load(); }); });
  while (store.stats().misses < 2) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  stop = true;
  const auto stopped = Clock::now();
  EXPECT_EQ(testing::CatchError([&] { second.get(); }).code(), ErrorCode::kCancelled);
  EXPECT_LT(Clock::now() - stopped, std::chrono::milliseconds(static_cast<int>(500 * testing::kSlowdown)));
  const auto [entry, known] = first.get();
  ASSERT_TRUE(entry);
  EXPECT_FALSE(known);
  EXPECT_EQ(store.stats().builds, 1);
  EXPECT_EQ(store.stats().cancelled_builds, 0);
}

}  // namespace
}  // namespace springblend::server
