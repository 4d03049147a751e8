// Load and faults against a real server process: many concurrent streams for a while (no errors, bounded
// memory, latency percentiles reported), kill -9 mid-upload and mid-solve then a restart on the same cache
// directory (nothing half-written is ever served), a cache filled past its budget (eviction, rebuild from
// disk), and a slow reader (server memory stays flat).
#include <fcntl.h>
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <sys/file.h>
#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <set>
#include <sstream>
#include <thread>

#include "integration/server_process.h"
#include "springblend/client.h"
#include "springblend/load.h"
#include "test_util.h"

namespace springblend {
namespace {

using testing::CylinderRig;
using testing::ServerProcess;
using testing::StatusOf;
using testing::SweepRequest;
using testing::TempDir;
using Clock = std::chrono::steady_clock;

using testing::RssMb;

// Samples a process's RSS every 100 ms until stopped; keeps every sample.
class RssSampler {
 public:
  explicit RssSampler(pid_t pid) : thread_([this, pid] {
    while (!stop_) {
      const double mb = RssMb(pid);
      {
        std::lock_guard lock(mutex_);
        samples_.push_back(mb);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  }) {}
  ~RssSampler() { Stop(); }
  void Stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  // Largest sample within the fraction [from, to) of the samples so far.
  double Max(double from = 0.0, double to = 1.0) const {
    std::lock_guard lock(mutex_);
    double best = 0.0;
    const size_t n = samples_.size();
    for (size_t i = static_cast<size_t>(from * n); i < static_cast<size_t>(to * n); ++i) best = std::max(best, samples_[i]);
    return best;
  }

 private:
  std::atomic<bool> stop_{false};
  mutable std::mutex mutex_;
  std::vector<double> samples_;
  std::thread thread_;
};

int EnvInt(const char* name, int fallback) {
  const char* value = std::getenv(name);
  return value ? std::atoi(value) : fallback;
}

TEST(LoadTest, ManyConcurrentStreamsRunWithoutErrorsInBoundedMemory) {
  TempDir cache;
  ServerProcess server(cache.path().string(), {"--workers", "2", "--queue", "64"});
  ASSERT_FALSE(server.address().empty());
  CylinderRig cylinder;
  const v1::Character c = Client({server.address()}).Upload(cylinder.rest, cylinder.targets);

  LoadOptions load;
  load.character_id = c.id();
  load.weights = {0.7, 0.4};
  load.streams = 16;
  load.frames_per_request = 4;
  load.max_requests = 100000;
  // CI runs 45 s; SPRINGBLEND_LOAD_SECONDS=300 for the few minutes of a longer soak.
  load.duration = std::chrono::seconds(EnvInt("SPRINGBLEND_LOAD_SECONDS", 45));
  RssSampler rss(server.pid());
  const LoadReport report = RunLoad({server.address()}, load);
  rss.Stop();
  std::cout << "load report: " << report.Json() << "\n";
  std::cout << "server RSS: first third peak " << rss.Max(0.0, 1.0 / 3) << " MiB, last third peak "
            << rss.Max(2.0 / 3, 1.0) << " MiB\n";
  EXPECT_EQ(report.errors, 0) << report.first_error;
  EXPECT_GT(report.requests, load.streams);
  EXPECT_EQ(report.frames, static_cast<long long>(report.requests) * load.frames_per_request);
  EXPECT_GT(report.p50_ms, 0.0);
  EXPECT_LE(report.p50_ms, report.p99_ms);
#if !defined(__SANITIZE_ADDRESS__)
  // Memory is flat once warm: the last third of the run peaks no more than 64 MiB above the first third.
  // (Under ASan freed memory fills its quarantine first, so RSS climbs there by design.)
  EXPECT_LT(rss.Max(2.0 / 3, 1.0), rss.Max(0.0, 1.0 / 3) + 64.0);
  EXPECT_LT(rss.Max(), 1024.0);
#endif
}

TEST(LoadTest, RefusesANonLoopbackAddress) {
  LoadOptions load;
  load.weights = {1};
  EXPECT_EQ(StatusOf([&] { RunLoad({"10.0.0.1:50051"}, load); }), grpc::StatusCode::INVALID_ARGUMENT);
}

std::set<std::string> FilesIn(const std::filesystem::path& dir) {
  std::set<std::string> names;
  for (const auto& f : std::filesystem::directory_iterator(dir)) names.insert(f.path().filename().string());
  return names;
}

// After a crash: every character the restarted server lists is whole (it builds and solves); no complete-
// looking file is half-written, and the restart removed the temporaries the killed writer left.
void ExpectOnlyWholeCharacters(const std::string& address, const std::filesystem::path& cache) {
  Client client({address});
  for (const auto& listed : client.List()) {
    const v1::Character c = client.Get(listed.id());
    EXPECT_EQ(c.id(), listed.id());
    const std::vector<double> weights(static_cast<size_t>(c.target_names_size()), 0.5);
    EXPECT_EQ(client.Solve(SweepRequest(c.id(), 1, weights), [](const v1::SolvedFrame&) {}), 1);
  }
  for (const auto& name : FilesIn(cache)) {
    EXPECT_TRUE(name.size() == 64 + 7 && name.substr(64) == ".sbchar") << "an unexpected file " << name;
  }
}

std::string ReadAll(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream bytes;
  bytes << in.rdbuf();
  return bytes.str();
}

TEST(FaultTest, KillMinusNineMidUploadServesNothingHalfWritten) {
  TempDir cache;
  auto server = std::make_unique<ServerProcess>(cache.path().string());
  ASSERT_FALSE(server->address().empty());
  // Half an upload, then the server dies under it.
  const TriangleMesh face = LoadMesh(testing::DataPath("face/generic_neutral_mesh.obj"));
  auto channel = grpc::CreateChannel(server->address(), grpc::InsecureChannelCredentials());
  auto stub = v1::CharacterService::NewStub(channel);
  grpc::ClientContext context;
  v1::Character response;
  auto writer = stub->UploadCharacter(&context, &response);
  v1::UploadChunk header;
  header.mutable_header()->set_vertex_count(static_cast<std::uint32_t>(face.vertices.rows()));
  header.mutable_header()->set_face_count(static_cast<std::uint32_t>(face.faces.rows()));
  header.mutable_header()->add_target_names("jaw");
  ASSERT_TRUE(writer->Write(header));
  v1::UploadChunk faces;
  faces.mutable_piece()->set_kind(v1::MeshPiece::FACES);
  faces.mutable_piece()->set_data(face.faces.data(), 12 * static_cast<size_t>(face.faces.rows()));
  ASSERT_TRUE(writer->Write(faces));
  server->Kill();
  EXPECT_NE(writer->Finish().error_code(), grpc::StatusCode::OK);

  // And an upload that dies while the rig builds or its file is written.
  server = std::make_unique<ServerProcess>(cache.path().string());
  std::thread uploader([&, address = server->address()] {
    v1::BuildOptions quick;
    quick.set_no_target_paths(true);  // the kill comes while the rig builds either way
    StatusOf([&] { Client({address}).Upload(face, {LoadMesh(testing::DataPath("face/jawOpen.obj"))}, quick); });
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(400));
  server->Kill();
  uploader.join();

  server = std::make_unique<ServerProcess>(cache.path().string());
  ExpectOnlyWholeCharacters(server->address(), cache.path());
  // A fresh upload of the same character works and is then served whole.
  CylinderRig cylinder;
  Client client({server->address()});
  const v1::Character c = client.Upload(cylinder.rest, cylinder.targets);
  EXPECT_EQ(client.Get(c.id()).id(), c.id());
}

TEST(FaultTest, ARestartRemovesStaleTemporariesAndNothingElse) {
  namespace fs = std::filesystem;
  TempDir cache, outside;
  const fs::path dir = cache.path();
  auto server = std::make_unique<ServerProcess>(dir.string());
  ASSERT_FALSE(server->address().empty());
  CylinderRig cylinder;
  const v1::Character c = Client({server->address()}).Upload(cylinder.rest, cylinder.targets);
  server->Kill();
  const std::string id = c.id(), other(64, 'a');
  const std::string character_file = ReadAll(dir / (id + ".sbchar"));
  ASSERT_FALSE(character_file.empty());

  // What writers killed mid-write leave: this version's names and earlier ones' (a decimal suffix).
  const std::vector<std::string> stale = {id + ".sbchar.tmp.4242.00f1e2d3c4b5a697",
                                          other + ".sbchar.tmp.7.12345678901234"};
  for (const auto& name : stale) std::ofstream(dir / name) << "half a character";
  // A writer in another replica sharing the directory, alive: it holds the lock on its temporary.
  const fs::path live = dir / (other + ".sbchar.tmp.99.0123456789abcdef");
  const int live_fd = ::open(live.c_str(), O_WRONLY | O_CREAT | O_CLOEXEC, 0644);
  ASSERT_GE(live_fd, 0);
  ASSERT_EQ(::flock(live_fd, LOCK_EX), 0);
  // Not ours, whatever they look like: kept as they are.
  const std::map<std::string, std::string> foreign = {
      {"notes.txt", "keep me"},
      {id + ".sbchar.tmp", "no pid, no suffix"},
      {id + ".sbchar.tmp.12.xyz", "a suffix that is not hex"},
      {id + ".sbchar.tmp.1.2.3", "one part too many"},
      {"F" + id.substr(1) + ".sbchar.tmp.1.2", "an upper-case id"},
      {id.substr(1) + ".sbchar.tmp.1.2", "a 63-digit id"},
  };
  for (const auto& [name, text] : foreign) std::ofstream(dir / name) << text;
  fs::create_directory(dir / (other + ".sbchar.tmp.5.6"));
  const std::string precious = outside.Write("precious", "outside the cache");
  fs::create_symlink(precious, dir / (other + ".sbchar.tmp.8.9"));

  const std::string log = outside.File("server.log");
  server = std::make_unique<ServerProcess>(dir.string(), std::vector<std::string>{}, log);
  ASSERT_FALSE(server->address().empty());
  for (const auto& name : stale) EXPECT_FALSE(fs::exists(dir / name)) << name << " was left";
  EXPECT_TRUE(fs::exists(live)) << "a live writer's temporary was removed";
  for (const auto& [name, text] : foreign) EXPECT_EQ(ReadAll(dir / name), text) << name;
  EXPECT_TRUE(fs::is_directory(dir / (other + ".sbchar.tmp.5.6")));
  EXPECT_TRUE(fs::is_symlink(dir / (other + ".sbchar.tmp.8.9")));
  EXPECT_EQ(ReadAll(precious), "outside the cache");
  EXPECT_EQ(ReadAll(dir / (id + ".sbchar")), character_file);
  EXPECT_THAT(ReadAll(log), ::testing::HasSubstr("removed 2 stale temporary files (1 in use by another writer, kept)"));
  ::close(live_fd);

  // The character is still listed and served, from its file.
  Client client({server->address()});
  const auto listed = client.List();
  ASSERT_EQ(listed.size(), 1u);
  EXPECT_EQ(listed[0].id(), id);
  EXPECT_EQ(client.Solve(SweepRequest(id, 2, {0.5, 0.5}), [](const v1::SolvedFrame&) {}), 2);
}

TEST(FaultTest, KillMinusNineMidSolveThenARestartServesTheSameFrames) {
  TempDir cache;
  auto server = std::make_unique<ServerProcess>(cache.path().string(), std::vector<std::string>{"--workers", "1"});
  CylinderRig cylinder;
  const v1::Character c = Client({server->address()}).Upload(cylinder.rest, cylinder.targets);
  std::vector<Points> before;
  Client({server->address()}).Solve(SweepRequest(c.id(), 3, {0.8, 0.3}), [&](const v1::SolvedFrame& f) {
    before.push_back(Client::Decode(f.positions()));
  });
  std::atomic<int> received{0};
  std::thread solver([&, address = server->address()] {
    StatusOf([&] {
      Client({address}).Solve(SweepRequest(c.id(), 2000, {1, 1}), [&](const v1::SolvedFrame&) { ++received; });
    });
  });
  while (received < 2) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  server->Kill();
  solver.join();
  EXPECT_LT(received, 2000);

  server = std::make_unique<ServerProcess>(cache.path().string());
  ExpectOnlyWholeCharacters(server->address(), cache.path());
  std::vector<Points> after;
  Client({server->address()}).Solve(SweepRequest(c.id(), 3, {0.8, 0.3}), [&](const v1::SolvedFrame& f) {
    after.push_back(Client::Decode(f.positions()));
  });
  ASSERT_EQ(after.size(), before.size());
  for (size_t i = 0; i < after.size(); ++i) EXPECT_LE(testing::MaxDistance(after[i], before[i]), 1e-9);
}

TEST(FaultTest, ACacheFilledPastItsBudgetEvictsAndRebuildsFromDisk) {
  TempDir cache;
  // 1 MiB holds one cylinder rig at most: each new upload evicts the least recently used.
  ServerProcess server(cache.path().string(), {"--memory-budget-mb", "1", "--metrics", "127.0.0.1:0"});
  CylinderRig cylinder;
  Client client({server.address()});
  std::vector<std::string> ids;
  for (int i = 0; i < 4; ++i) {
    v1::BuildOptions options;
    options.set_bending_stiffness(1.0 + 0.25 * i);  // another character each time
    ids.push_back(client.Upload(cylinder.rest, cylinder.targets, options).id());
  }
  EXPECT_EQ(std::set<std::string>(ids.begin(), ids.end()).size(), 4u);
  EXPECT_EQ(client.List().size(), 4u);  // all on disk
  // Every one still solves: evicted ones are rebuilt from the cache directory.
  for (const auto& id : ids) EXPECT_EQ(client.Solve(SweepRequest(id, 1, {0.5, 0.5}), [](const v1::SolvedFrame&) {}), 1);
  const std::string metrics = testing::HttpGet(server.metrics_port(), "/metrics");
  EXPECT_THAT(metrics, ::testing::ContainsRegex("springblend_cache_evictions_total [1-9]"));
  EXPECT_THAT(metrics, ::testing::ContainsRegex("springblend_cache_rebuilds_from_disk_total [1-9]"));
  EXPECT_THAT(metrics, ::testing::ContainsRegex("springblend_cache_characters [123]\n"));
}

// The frames the server has solved so far, from its metrics page.
long long FramesSolved(int metrics_port) {
  const std::string page = testing::HttpGet(metrics_port, "/metrics");
  const std::string key = "\nspringblend_frames_solved_total ";
  const auto at = page.find(key);
  return at == std::string::npos ? -1 : std::stoll(page.substr(at + key.size()));
}

TEST(FaultTest, ASlowReaderDoesNotGrowServerMemory) {
  TempDir cache;
  ServerProcess server(cache.path().string(), {"--workers", "2", "--metrics", "127.0.0.1:0"});
  const TriangleMesh face = LoadMesh(testing::DataPath("face/generic_neutral_mesh.obj"));
  v1::BuildOptions quick;
  quick.set_no_target_paths(true);  // linear frames below: the paths would only slow the upload
  const v1::Character c =
      Client({server.address()}).Upload(face, {LoadMesh(testing::DataPath("face/jawOpen.obj"))}, quick);
  // Linear frames are cheap to make and as large as any: a server that queued them would grow fast.
  v1::SolveRequest request = SweepRequest(c.id(), 5000, {1.0});
  request.mutable_options()->set_linear(true);
  auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto stub = v1::SolveService::NewStub(channel);
  grpc::ClientContext context;
  auto reader = stub->Solve(&context, request);
  v1::SolvedFrame frame;
  ASSERT_TRUE(reader->Read(&frame));
  const double frame_mb = static_cast<double>(frame.ByteSizeLong()) / (1 << 20);
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  const double start_mb = RssMb(server.pid());
  int read = 1;
  const auto until = Clock::now() + std::chrono::seconds(6);
  while (Clock::now() < until && reader->Read(&frame)) {
    ++read;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  const double end_mb = RssMb(server.pid());
  const long long solved = FramesSolved(server.metrics_port());
  context.TryCancel();
  while (reader->Read(&frame)) {
  }
  reader->Finish();
  std::cout << "slow reader: read " << read << " frames of " << frame_mb << " MiB in 6 s; the server solved " << solved
            << "; server RSS " << start_mb << " -> " << end_mb << " MiB\n";
  EXPECT_LT(read, 1000);
  // The server keeps pace with the reader: it solves a frame only once the previous one is handed to gRPC, so
  // it is ahead by at most what the HTTP/2 flow-control windows hold (a few MiB), never the whole request.
  EXPECT_GE(solved, read);
  EXPECT_LT(static_cast<double>(solved - read) * frame_mb, 16.0) << "frames in flight: " << solved - read;
#if !defined(__SANITIZE_ADDRESS__)
  // (Under ASan freed memory sits in its quarantine, so RSS says little there.) Queued, the 5000 frames would
  // take 5000 * frame_mb, about 390 MiB.
  EXPECT_LT(end_mb - start_mb, 32.0);
#endif
}

}  // namespace
}  // namespace springblend
