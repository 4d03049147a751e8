// Hardening IV against real server processes: an OK never loses a character (a delete during a build, then an
// upload), a damaged or missing cache file heals on the next upload, a cache file cut short under a served
// character drops it rather than fail every frame for good, a FIFO renamed over a cache file during its rebuild
// is never opened, and the server refuses configurations it cannot honour (a token listed twice).
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "grpc/health/v1/health.grpc.pb.h"
#include "integration/server_process.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using testing::CylinderRig;
using testing::ServerProcess;
using testing::SweepRequest;
using testing::TempDir;
using Clock = std::chrono::steady_clock;

std::string ReadText(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

std::chrono::seconds Seconds(int n) { return std::chrono::seconds(static_cast<int>(n * testing::kSlowdown)); }

std::string CacheFile(const std::string& cache, const std::string& id) { return cache + "/" + id + ".sbchar"; }

// The frames of a short sweep (positions as sent), or the error's code.
struct Sweep {
  int code = 0;
  std::string message;
  std::vector<std::string> positions;
};
Sweep Solve(const std::string& address, const std::string& id, const std::vector<double>& end = {0.9, 0.6}) {
  Client client({address, Seconds(60)});
  Sweep sweep;
  try {
    client.Solve(SweepRequest(id, 3, end),
                 [&](const v1::SolvedFrame& frame) { sweep.positions.push_back(frame.positions()); });
  } catch (const ClientError& e) {
    sweep.code = e.code();
    sweep.message = e.what();
  }
  return sweep;
}

// Uploads the cylinder (with its target paths: the part of a cache file a rig reads as frames need it).
v1::Character UploadCylinder(const std::string& address) {
  CylinderRig cylinder;
  Client client({address, Seconds(120)});
  return client.Upload(cylinder.rest, cylinder.targets, {}, "cylinder");
}

// The cube with its target paths: a build of a few seconds, long enough to act on while it runs.
v1::Character UploadCube(const std::string& address, std::chrono::milliseconds timeout = Seconds(300)) {
  Client client({address, timeout});
  return client.Upload(LoadMesh(testing::DataPath("cube/cube.obj")),
                       {LoadMesh(testing::DataPath("cube/poses-1_cube-1.obj"))}, {}, "cube");
}

// An upload of the cube on a thread of its own, returned once the server says it is building it (its id in *id);
// an invalid future when the build was over before that was seen.
std::future<v1::Character> StartCubeUpload(const std::string& address, std::string* id) {
  RigTarget target;
  target.mesh = LoadMesh(testing::DataPath("cube/poses-1_cube-1.obj"));
  *id = CharacterId(LoadMesh(testing::DataPath("cube/cube.obj")), {target});
  auto upload = std::async(std::launch::async, [address] { return UploadCube(address); });
  Client client({address, Seconds(10)});
  const auto until = Clock::now() + Seconds(60);
  while (Clock::now() < until) {
    try {
      const v1::CharacterState state = client.Get(*id, false, true).state();
      if (state == v1::CHARACTER_STATE_BUILDING) return upload;
      if (state == v1::CHARACTER_STATE_READY) break;
    } catch (const ClientError&) {  // NOT_FOUND until the pieces are in
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  upload.wait();
  return {};
}

// Item 1: a delete during a build marked the build deleted, and an upload sent after the delete joined it: OK with
// cache_hit, then NOT_FOUND everywhere and no file. An upload after a delete must end with the character stored.
TEST(HardeningIV, AnUploadAfterADeleteDuringTheBuildIsKept) {
  TempDir dir;
  const std::string cache = dir.File("cache");
  ServerProcess server(cache, {"--workers", "2"});
  ASSERT_FALSE(server.address().empty());
  std::string id;
  auto first = StartCubeUpload(server.address(), &id);
  ASSERT_TRUE(first.valid()) << "the build ended too soon";
  Client client({server.address(), Seconds(120)});
  client.Delete(id);  // OK: the build in flight is not kept
  const v1::Character again = UploadCube(server.address());
  EXPECT_EQ(again.id(), id);
  EXPECT_EQ(first.get().id(), id);  // the first upload finished for its caller
  // Sent after the delete, the second upload's character is kept: in memory, in the directory, served.
  EXPECT_EQ(client.Get(id, false, true).state(), v1::CHARACTER_STATE_READY);
  EXPECT_TRUE(std::filesystem::is_regular_file(CacheFile(cache, id)));
  const Sweep sweep = Solve(server.address(), id, {0.9});
  EXPECT_EQ(sweep.code, 0) << sweep.message;
  EXPECT_EQ(sweep.positions.size(), 3u);
  // And a restart on the directory serves it too.
  server.Stop();
  ServerProcess restarted(cache, {"--workers", "1"});
  EXPECT_TRUE(Solve(restarted.address(), id, {0.9}).positions == sweep.positions);
}

// Item 2: with a cache directory shared by two replicas, one deleted a character the other held in memory; a
// re-upload to the holder answered cache_hit and wrote no file, so the other replica (and a restarted holder)
// said NOT_FOUND. The same after the file was replaced with garbage. A re-upload leaves a valid file.
TEST(HardeningIV, AReuploadRepairsAMissingOrDamagedCacheFile) {
  TempDir dir;
  const std::string cache = dir.File("cache");
  const std::string log = dir.File("holder.log");
  ServerProcess holder(cache, {"--workers", "1"}, log);
  ServerProcess other(cache, {"--workers", "1"});
  ASSERT_FALSE(holder.address().empty());
  ASSERT_FALSE(other.address().empty());
  const std::string id = UploadCylinder(holder.address()).id();
  const Sweep expected = Solve(holder.address(), id);
  ASSERT_EQ(expected.code, 0) << expected.message;
  const std::string file = CacheFile(cache, id);

  Client client({other.address(), Seconds(60)});
  client.Delete(id);
  ASSERT_FALSE(std::filesystem::exists(file));
  EXPECT_TRUE(UploadCylinder(holder.address()).cache_hit());
  ASSERT_TRUE(std::filesystem::is_regular_file(file)) << "the re-upload wrote no file";
  const Sweep first = Solve(other.address(), id);
  EXPECT_EQ(first.code, 0) << "the other replica cannot serve it: " << first.message;
  EXPECT_TRUE(first.positions == expected.positions);
  EXPECT_TRUE(client.Get(id).summary().paths_loaded());
  client.Delete(id);  // out of the other replica's memory (and the file gone again)
  ASSERT_FALSE(std::filesystem::exists(file));

  // Garbage renamed over the file (as another writer would): the re-upload writes it anew.
  EXPECT_TRUE(UploadCylinder(holder.address()).cache_hit());
  const std::string garbage = dir.Write("garbage", std::string(4096, 'x'));
  std::filesystem::rename(garbage, file);
  EXPECT_TRUE(UploadCylinder(holder.address()).cache_hit());
  EXPECT_GT(std::filesystem::file_size(file), 4096u);
  const Sweep served = Solve(other.address(), id);
  EXPECT_EQ(served.code, 0) << served.message;
  EXPECT_TRUE(served.positions == expected.positions);
  EXPECT_TRUE(client.Get(id).summary().paths_loaded()) << "the paths were not in the file written anew";
  EXPECT_THAT(ReadText(log), HasSubstr("written anew from the character in memory"));
}

// Item 3: a cache file cut short while its character was served failed every frame with INTERNAL, List said
// READY, and a re-upload answered cache_hit without repairing anything. Now the read failure drops the
// character: List no longer says READY, and the next upload builds it and writes its file again.
TEST(HardeningIV, ACacheFileCutShortWhileServedIsRepairedByTheNextUpload) {
  TempDir dir;
  const std::string cache = dir.File("cache");
  ServerProcess server(cache, {"--workers", "1"});
  ASSERT_FALSE(server.address().empty());
  const std::string id = UploadCylinder(server.address()).id();
  const Sweep expected = Solve(server.address(), id);
  ASSERT_EQ(expected.code, 0) << expected.message;
  // Cut the file after its character and the paths' checksum: every path sample is gone.
  const std::string file = CacheFile(cache, id);
  const std::string bytes = ReadText(file);
  std::uint64_t payload = 0;
  std::memcpy(&payload, bytes.data() + 40, sizeof(payload));  // "SBCHAR02" | SHA-256 | u64 length | payload ...
  ASSERT_LT(48 + payload + 32, bytes.size());
  std::filesystem::resize_file(file, 48 + payload + 32);
  const Sweep failed = Solve(server.address(), id);
  EXPECT_EQ(failed.code, grpc::StatusCode::INTERNAL) << failed.message;
  EXPECT_THAT(failed.message, HasSubstr("cut short"));
  EXPECT_THAT(failed.message, HasSubstr("dropped"));
  Client client({server.address(), Seconds(60)});
  for (const v1::Character& c : client.List()) {
    EXPECT_NE(c.id(), id) << "a character whose file is cut short is listed (state " << c.state() << ")";
  }
  const v1::Character again = UploadCylinder(server.address());
  EXPECT_FALSE(again.cache_hit());
  const Sweep repaired = Solve(server.address(), id);
  EXPECT_EQ(repaired.code, 0) << repaired.message;
  EXPECT_TRUE(repaired.positions == expected.positions);
  EXPECT_GT(std::filesystem::file_size(file), 48 + payload + 32);
}

// Item 4: the cache file was checked through one descriptor and opened again by name when the rig loaded its
// paths; a FIFO renamed over it in between blocked the only build thread for good (and SIGTERM with it). The rig
// now reads through the descriptor that was checked.
TEST(HardeningIV, AFifoRenamedOverACacheFileDuringItsRebuildIsNeverOpened) {
  TempDir dir;
  const std::string cache = dir.File("cache");
  std::string id;
  {
    ServerProcess first(cache, {"--workers", "1"});
    ASSERT_FALSE(first.address().empty());
    id = UploadCube(first.address()).id();
  }
  ServerProcess server(cache, {"--workers", "1", "--build-workers", "1", "--drain-seconds", "3"});
  ASSERT_FALSE(server.address().empty());
  Client client({server.address(), Seconds(60)});
  auto rebuild = std::async(std::launch::async, [&] {
    try {
      return Client({server.address(), Seconds(60)}).Get(id).state();
    } catch (const ClientError&) {
      return v1::CHARACTER_STATE_UNSPECIFIED;
    }
  });
  // Once the rebuild's build has begun (the file read and checked), a FIFO takes the file's name.
  for (;;) {
    const v1::Character c = client.Get(id, false, true);
    if (c.state() == v1::CHARACTER_STATE_READY) FAIL() << "the rebuild ended before the FIFO came";
    if (c.state() == v1::CHARACTER_STATE_BUILDING && c.build().stage() != "queued") break;
  }
  const std::string fifo = dir.File("fifo");
  ASSERT_EQ(mkfifo(fifo.c_str(), 0644), 0);
  std::filesystem::rename(fifo, CacheFile(cache, id));
  const bool ended = rebuild.wait_for(Seconds(60)) == std::future_status::ready;
  if (!ended) server.Kill();  // blocked on the FIFO for good: SIGTERM would not stop it
  ASSERT_TRUE(ended) << "the rebuild hung";
  EXPECT_EQ(rebuild.get(), v1::CHARACTER_STATE_READY);
  EXPECT_TRUE(client.Get(id).summary().paths_loaded());
  const Sweep sweep = Solve(server.address(), id, {0.9});
  EXPECT_EQ(sweep.code, 0) << sweep.message;
}

// Item 9: a token listed twice kept whichever role came last (a --token full token silently became solve-only).
// The server refuses to start, naming the line (and never the token).
TEST(HardeningIV, ATokenListedTwiceIsRefusedNamingTheLine) {
  TempDir dir;
  const std::string file = dir.Write("tokens", "# roles\nfull alpha-token\nsolve beta-token\n\nsolve alpha-token\n");
  testing::ServerRun run = testing::RunServer(dir, {"--workers", "1", "--listen", "127.0.0.1:0", "--tokens-file", file});
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_THAT(run.output, HasSubstr("--tokens-file " + file + ":5: the token of --tokens-file " + file + ":2 again"));
  EXPECT_THAT(run.output, Not(HasSubstr("alpha-token")));
  EXPECT_THAT(run.output, Not(HasSubstr("listening on")));
  // A --token given again in the file.
  const std::string other = dir.Write("other", "solve gamma-token\n");
  run = testing::RunServer(dir, {"--workers", "1", "--listen", "127.0.0.1:0", "--token", "gamma-token",
                                 "--tokens-file", other});
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_THAT(run.output, HasSubstr("--tokens-file " + other + ":1: the token of --token again"));
}

// Item 15: health Watch streams need no token (fine) but were unbounded in number (2,000 held 36 MiB). At most
// 100 are open at once, on the main port and on --health-address each; one more is refused at once, Check is
// never refused, and a closed Watch makes room.
TEST(HardeningIV, HealthWatchStreamsAreBounded) {
  TempDir dir;
  ServerProcess server(dir.File("cache"), {"--workers", "1", "--token", "s3cret", "--health-address", "127.0.0.1:0"});
  ASSERT_FALSE(server.address().empty());
  for (const std::string& address : {server.address(), server.health_address()}) {
    auto stub = grpc::health::v1::Health::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
    struct Watch {
      grpc::ClientContext context;
      std::unique_ptr<grpc::ClientReader<grpc::health::v1::HealthCheckResponse>> reader;
      bool finished = false;
      ~Watch() {
        context.TryCancel();
        if (reader && !finished) reader->Finish();
      }
    };
    // Opened and answered (SERVING), or refused: the status.
    const auto open = [&](Watch* watch) {
      watch->context.set_deadline(std::chrono::system_clock::now() + Seconds(30));
      watch->reader = stub->Watch(&watch->context, grpc::health::v1::HealthCheckRequest());
      grpc::health::v1::HealthCheckResponse response;
      if (watch->reader->Read(&response)) return grpc::Status::OK;
      watch->finished = true;
      return watch->reader->Finish();
    };
    std::vector<std::unique_ptr<Watch>> watches;
    for (int i = 0; i < 100; ++i) {
      watches.push_back(std::make_unique<Watch>());
      const grpc::Status status = open(watches.back().get());
      ASSERT_TRUE(status.ok()) << address << ": watch " << i << ": " << status.error_message();
    }
    Watch refused;
    const grpc::Status status = open(&refused);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << address << ": " << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr("100 health Watch streams open"));
    Client client({address, Seconds(10)});
    EXPECT_TRUE(client.Healthy()) << "Check is never refused";
    // One closed makes room (its call ends on the server a moment later).
    watches.erase(watches.begin());
    const auto until = Clock::now() + Seconds(10);
    grpc::Status again;
    do {
      Watch another;
      again = open(&another);
      if (again.ok()) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    } while (Clock::now() < until);
    EXPECT_TRUE(again.ok()) << address << ": " << again.error_message();
  }
}

size_t Count(const std::string& text, const std::string& part) {
  size_t n = 0;
  for (size_t at = text.find(part); at != std::string::npos; at = text.find(part, at + 1)) ++n;
  return n;
}

// Item 10: an upload that joined another client's build was logged "rebuilding from the cache directory", and one
// whose client had already gone was logged (and counted) OK when the build ended. The log says what each saw.
TEST(HardeningIV, LogsSayWhatTheClientSaw) {
  TempDir dir;
  const std::string log = dir.File("server.log");
  ServerProcess server(dir.File("cache"), {"--workers", "2"}, log);
  ASSERT_FALSE(server.address().empty());
  std::string id;
  auto first = StartCubeUpload(server.address(), &id);
  ASSERT_TRUE(first.valid()) << "the build ended too soon";
  // A second client joins the build, then gives up (its deadline) while the first still wants it.
  EXPECT_EQ(testing::StatusOf([&] { UploadCube(server.address(), std::chrono::milliseconds(300)); }),
            grpc::StatusCode::DEADLINE_EXCEEDED);
  EXPECT_FALSE(first.get().cache_hit());
  server.Stop();
  const std::string text = ReadText(log);
  EXPECT_THAT(text, HasSubstr("joins the build already in flight"));
  EXPECT_EQ(Count(text, "access UploadCharacter OK"), 1u) << text;
  EXPECT_EQ(Count(text, "access UploadCharacter DEADLINE_EXCEEDED"), 1u) << text;
  EXPECT_THAT(text, HasSubstr("the deadline passed while the character was being built"));
}

}  // namespace
}  // namespace springblend
