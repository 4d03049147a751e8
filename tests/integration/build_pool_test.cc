// Long builds on a farm server (a real server process): they run on build workers of their own, so solves,
// sessions and metadata calls are answered while face-size builds run; their progress can be followed; a build
// nobody waits for any more stops within seconds; SIGTERM during a build exits within the drain.
//
// The face builds here never finish (each is abandoned a few seconds in), so the suite stays short.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <thread>

#include "server_process.h"
#include "springblend/client.h"
#include "springblend/mesh.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using Clock = std::chrono::steady_clock;
using testing::DataPath;
using testing::TempDir;
using testing::CylinderRig;
using testing::HttpGet;
using testing::ServerProcess;
using testing::SweepRequest;

double Seconds(Clock::time_point since) { return std::chrono::duration<double>(Clock::now() - since).count(); }

double Metric(int port, const std::string& name) {
  const std::string text = HttpGet(port, "/metrics");
  const auto at = text.find("\n" + name + " ");
  return at == std::string::npos ? -1.0 : std::stod(text.substr(at + name.size() + 2));
}

struct Face {
  TriangleMesh neutral = LoadMesh(DataPath("face/generic_neutral_mesh.obj"));
  std::vector<TriangleMesh> expressions = {
      LoadMesh(DataPath("face/jawOpen.obj")), LoadMesh(DataPath("face/mouthClose.obj")),
      LoadMesh(DataPath("face/mouthFunnel.obj")), LoadMesh(DataPath("face/mouthSmile_L.obj")),
      LoadMesh(DataPath("face/mouthStretch_L.obj"))};
};

// An upload of the face on its own thread, with a client deadline; records the id and the progress it saw.
class FaceUpload {
 public:
  FaceUpload(const std::string& address, const Face& face, double bending, std::chrono::seconds timeout)
      : thread_([this, address, &face, bending, timeout] {
          Client client({address, timeout});
          v1::BuildOptions options;
          options.set_bending_stiffness(bending);  // another character per value
          // Five expressions with the densest paths: a build of minutes, which must outlast its client's deadline
          // however fast the paths become.
          options.set_path_intervals(128);
          try {
            client.Upload(face.neutral, face.expressions, options, "face", [this](const std::string& id,
                                                                            const v1::BuildProgress& p) {
              std::lock_guard lock(mutex_);
              id_ = id;
              progress_.push_back(p);
            });
          } catch (const ClientError& e) {
            std::lock_guard lock(mutex_);
            code_ = e.code();
            error_ = e.what();
          }
          done_ = true;
        }) {}
  ~FaceUpload() { thread_.join(); }
  bool done() const { return done_; }
  std::string id() const {
    std::lock_guard lock(mutex_);
    return id_;
  }
  std::vector<v1::BuildProgress> progress() const {
    std::lock_guard lock(mutex_);
    return progress_;
  }
  int code() const {
    std::lock_guard lock(mutex_);
    return code_;
  }
  std::string error() const {
    std::lock_guard lock(mutex_);
    return error_;
  }

 private:
  mutable std::mutex mutex_;
  std::string id_, error_;
  std::vector<v1::BuildProgress> progress_;
  int code_ = 0;
  std::atomic<bool> done_{false};
  std::thread thread_;
};

TEST(BuildPoolTest, SolvesAndMetadataAreAnsweredWhileFaceBuildsRunAndAbandonedBuildsStop) {
  TempDir cache;
  ServerProcess server((cache.path() / "cache").string(),
                       {"--workers", "2", "--build-workers", "1", "--build-queue", "4", "--metrics", "127.0.0.1:0"});
  ASSERT_FALSE(server.address().empty());
  CylinderRig cylinder;
  Client client({server.address(), std::chrono::seconds(60)});
  const v1::Character small = client.Upload(cylinder.rest, cylinder.targets, {}, "cylinder");
  const v1::Character spare = client.Upload(cylinder.rest, {cylinder.targets[0]}, {}, "spare");
  const Face face;
  const double cancelled_before = Metric(server.metrics_port(), "springblend_cache_cancelled_builds_total");
  {
    // Two face builds: one runs on the build worker, the other waits in the build queue. Their clients give
    // up after 12 and 14 s.
    FaceUpload first(server.address(), face, 0.1, std::chrono::seconds(12));
    FaceUpload second(server.address(), face, 0.2, std::chrono::seconds(14));
    // Wait until a build runs (its progress seen by the first client).
    const auto began = Clock::now();
    while (first.progress().empty() && Seconds(began) < 10) std::this_thread::sleep_for(std::chrono::milliseconds(50));
    ASSERT_FALSE(first.progress().empty()) << "no build progress within 10 s";
    EXPECT_EQ(Metric(server.metrics_port(), "springblend_build_workers_busy"), 1);
    // While they build: a cylinder solve, Get, List and Delete are answered at once.
    Client quick({server.address(), std::chrono::seconds(5)});
    for (int i = 0; i < 3; ++i) {
      const auto asked = Clock::now();
      int frames = 0;
      quick.Solve(SweepRequest(small.id(), 3, {0.6, 0.3}), [&](const v1::SolvedFrame&) { ++frames; });
      EXPECT_EQ(frames, 3);
      EXPECT_LT(Seconds(asked), 2.0) << "a cylinder solve waited behind the builds";
    }
    auto asked = Clock::now();
    EXPECT_EQ(quick.Get(small.id()).state(), v1::CHARACTER_STATE_READY);
    // Listed: the two built, and the two being built (once both uploads' pieces are checked).
    const std::vector<v1::Character> listed = quick.List();
    EXPECT_GE(listed.size(), 3u);
    for (const v1::Character& c : listed) {
      if (c.id() == small.id() || c.id() == spare.id()) {
        EXPECT_EQ(c.state(), v1::CHARACTER_STATE_READY);
      } else {
        EXPECT_EQ(c.state(), v1::CHARACTER_STATE_BUILDING) << c.id();
        EXPECT_EQ(c.name(), "face");
      }
    }
    quick.Delete(spare.id());
    EXPECT_LT(Seconds(asked), 1.0) << "metadata calls waited behind the builds";
    // The builds' state, without waiting: one running (its stage past the queue), the other queued (which is
    // which depends on which upload's pieces were checked first).
    while (second.id().empty() && !second.done() && Seconds(began) < 20) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    ASSERT_FALSE(second.id().empty());
    const v1::Character a = quick.Get(first.id(), false, true), b = quick.Get(second.id(), false, true);
    EXPECT_EQ(a.state(), v1::CHARACTER_STATE_BUILDING);
    EXPECT_EQ(b.state(), v1::CHARACTER_STATE_BUILDING);
    EXPECT_EQ(a.name(), "face");
    EXPECT_EQ((a.build().stage() == "queued") + (b.build().stage() == "queued"), 1)
        << a.build().stage() << ", " << b.build().stage();
    EXPECT_GT(a.build().elapsed_ms(), 0.0);
    // Abandoned: once both clients' deadlines pass, nobody waits for the builds and they stop.
    while (!(first.done() && second.done()) && Seconds(began) < 60) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    EXPECT_EQ(first.code(), grpc::StatusCode::DEADLINE_EXCEEDED) << first.error();
    EXPECT_EQ(second.code(), grpc::StatusCode::DEADLINE_EXCEEDED) << second.error();
    const auto abandoned = Clock::now();
    while (Metric(server.metrics_port(), "springblend_build_workers_busy") != 0 && Seconds(abandoned) < 10) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    EXPECT_EQ(Metric(server.metrics_port(), "springblend_build_workers_busy"), 0);
    EXPECT_LT(Seconds(abandoned), 5.0) << "an abandoned build kept its worker";
    EXPECT_EQ(Metric(server.metrics_port(), "springblend_build_queue_depth"), 0);
  }
  // Stopped builds keep nothing: the face is unknown, the cylinder still served.
  EXPECT_GE(Metric(server.metrics_port(), "springblend_cache_cancelled_builds_total"), cancelled_before + 1);
  Client after({server.address(), std::chrono::seconds(5)});
  EXPECT_EQ(after.List().size(), 1u);
  int frames = 0;
  after.Solve(SweepRequest(small.id(), 2, {1.0, 0.0}), [&](const v1::SolvedFrame&) { ++frames; });
  EXPECT_EQ(frames, 2);
}

TEST(BuildPoolTest, ASolveOfACharacterBeingBuiltWaitsWithinItsDeadline) {
  TempDir cache;
  ServerProcess server((cache.path() / "cache").string(), {"--workers", "2", "--metrics", "127.0.0.1:0"});
  ASSERT_FALSE(server.address().empty());
  const Face face;
  FaceUpload upload(server.address(), face, 0.1, std::chrono::seconds(20));
  const auto began = Clock::now();
  while (upload.id().empty() && Seconds(began) < 10) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  ASSERT_FALSE(upload.id().empty());
  // A one-frame solve of it with a 2 s deadline: it waits for the build, then says why it gave up.
  Client solver({server.address(), std::chrono::seconds(2)});
  v1::SolveRequest request;
  request.set_character_id(upload.id());
  request.add_frames()->add_weights(0.5);
  const auto asked = Clock::now();
  try {
    solver.Solve(request, [](const v1::SolvedFrame&) {});
    ADD_FAILURE() << "a solve of a character still building answered within 2 s";
  } catch (const ClientError& e) {
    EXPECT_EQ(e.code(), grpc::StatusCode::DEADLINE_EXCEEDED) << e.what();
  }
  EXPECT_LT(Seconds(asked), 5.0);
  // The build goes on for the upload that still waits.
  EXPECT_EQ(solver.Get(upload.id(), false, true).state(), v1::CHARACTER_STATE_BUILDING);
  EXPECT_EQ(Metric(server.metrics_port(), "springblend_workers_busy"), 0) << "a solve held a worker while waiting";
}

TEST(BuildPoolTest, SigtermDuringABuildExitsWithinTheDrain) {
  TempDir cache;
  ServerProcess server((cache.path() / "cache").string(), {"--drain-seconds", "1"});
  ASSERT_FALSE(server.address().empty());
  const Face face;
  FaceUpload upload(server.address(), face, 0.1, std::chrono::seconds(120));
  const auto began = Clock::now();
  while (upload.progress().empty() && Seconds(began) < 10) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  ASSERT_FALSE(upload.progress().empty());
  const auto stopped = Clock::now();
  EXPECT_EQ(server.Stop(), 0);
  // The drain (1 s), then the build stops within an iteration: generous for a loaded machine.
  EXPECT_LT(Seconds(stopped), 1.0 + 4.0) << "SIGTERM waited for the build";
  while (!upload.done() && Seconds(stopped) < 10) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  EXPECT_TRUE(upload.done());
  EXPECT_NE(upload.code(), 0) << "an upload cut by the shutdown was answered as if built";
}

}  // namespace
}  // namespace springblend
