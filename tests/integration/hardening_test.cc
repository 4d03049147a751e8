// Hardening III against a real server: ports that are taken (no SO_REUSEPORT), a tokens file without tokens,
// flags out of range, and values finite as doubles but not as the float32 the answers carry (pins, colliders,
// in-between weights, combination products); the memory Solve requests and sessions really hold, the watchdog's
// reasons, the idle clock, cache files that are not regular or cannot be written, the Bearer scheme. Each
// refusal names the flag or the field; a normal client is served meanwhile.
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "integration/server_process.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using testing::CylinderRig;
using testing::RunServer;
using testing::ServerProcess;
using testing::ServerRun;
using testing::SweepRequest;
using testing::TempDir;

// A loopback port free at the time of asking.
int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof(address);
  bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address));
  getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length);
  close(fd);
  return ntohs(address.sin_port);
}

TEST(HardeningStart, ASecondServerOnATakenPortDoesNotStart) {
  TempDir dir;
  ServerProcess first(dir.File("first"), {"--workers", "1"});
  ASSERT_FALSE(first.address().empty());
  const ServerRun second = RunServer(dir, {"--workers", "1", "--listen", first.address()});
  EXPECT_EQ(second.exit_code, 2) << second.output;
  EXPECT_THAT(second.output, HasSubstr("--listen " + first.address()));
  EXPECT_THAT(second.output, HasSubstr("taken"));
  EXPECT_THAT(second.output, Not(HasSubstr("listening on")));
  Client client({first.address(), std::chrono::seconds(5)});
  EXPECT_TRUE(client.Healthy()) << "the first server keeps its port";
}

TEST(HardeningStart, AHealthAddressEqualToListenIsRefused) {
  TempDir dir;
  const std::string address = "127.0.0.1:" + std::to_string(FreePort());
  const ServerRun run = RunServer(dir, {"--workers", "1", "--listen", address, "--health-address", address});
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_THAT(run.output, HasSubstr("--health-address " + address + " is the port of --listen " + address));
}

TEST(HardeningStart, ATokensFileWithoutTokensIsRefused) {
  TempDir dir;
  for (const std::string text : {"", "# only a comment\n\n   \n# another\n"}) {
    const std::string file = dir.Write("tokens", text);
    const ServerRun run = RunServer(dir, {"--workers", "1", "--listen", "127.0.0.1:0", "--tokens-file", file});
    EXPECT_EQ(run.exit_code, 2) << run.output;
    EXPECT_THAT(run.output, HasSubstr("--tokens-file " + file + " has no tokens: refusing to start with "
                                      "authentication off; omit --tokens-file to run open"));
  }
}

TEST(HardeningStart, FlagsOutOfRangeAreRefusedNamingTheFlag) {
  TempDir dir;
  const std::vector<std::pair<std::vector<std::string>, std::string>> cases = {
      {{"--metrics", "127.0.0.1:99999"}, "--metrics 127.0.0.1:99999"},
      {{"--metrics", ":abc"}, "--metrics :abc"},
      {{"--metrics", "127.0.0.1:abc"}, "--metrics 127.0.0.1:abc"},
      {{"--max-frames", "0"}, "--max-frames"},
      {{"--max-vertices", "-1"}, "--max-vertices"},
      {{"--max-upload-bytes", "-1"}, "--max-upload-bytes"},
  };
  for (const auto& [flags, expected] : cases) {
    std::vector<std::string> arguments = {"--workers", "1", "--listen", "127.0.0.1:0"};
    arguments.insert(arguments.end(), flags.begin(), flags.end());
    const ServerRun run = RunServer(dir, arguments);
    EXPECT_NE(run.exit_code, 0) << expected;
    EXPECT_NE(run.exit_code, 124) << expected << ": the server started";
    EXPECT_THAT(run.output, HasSubstr(expected));
    EXPECT_THAT(run.output, Not(HasSubstr("stoi")));
    EXPECT_THAT(run.output, Not(HasSubstr("listening on")));
    if (flags[0] != "--metrics") {
      EXPECT_THAT(run.output, HasSubstr("range")) << expected << ": " << run.output;
    }
  }
}

class Float32Test : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    cache_ = new TempDir();
    server_ = new ServerProcess(cache_->File("cache"), {"--workers", "2"});
    ASSERT_FALSE(server_->address().empty()) << "the server did not start";
    cylinder_ = new CylinderRig;
    Client client({server_->address(), std::chrono::seconds(60)});
    character_ = new v1::Character(client.Upload(cylinder_->rest, cylinder_->targets, {}, "cylinder"));
  }
  static void TearDownTestSuite() {
    delete server_;
    delete cache_;
    delete cylinder_;
    delete character_;
  }

  static v1::SolveRequest Normal() { return SweepRequest(character_->id(), 2, {0.6, 0.3}); }

  // The Solve's status; `frames` counts the answers that came before it.
  static grpc::Status Solve(const v1::SolveRequest& request, int* frames = nullptr) {
    const auto channel = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
    auto stub = v1::SolveService::NewStub(channel);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    auto reader = stub->Solve(&context, request);
    v1::SolvedFrame frame;
    int count = 0;
    while (reader->Read(&frame)) ++count;
    if (frames) *frames = count;
    return reader->Finish();
  }

  static void ExpectRefused(const v1::SolveRequest& request, const std::string& message) {
    int frames = -1;
    const grpc::Status status = Solve(request, &frames);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << message << ": " << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr(message));
    EXPECT_EQ(frames, 0) << message;
  }

  static TempDir* cache_;
  static ServerProcess* server_;
  static CylinderRig* cylinder_;
  static v1::Character* character_;
};

TempDir* Float32Test::cache_ = nullptr;
ServerProcess* Float32Test::server_ = nullptr;
CylinderRig* Float32Test::cylinder_ = nullptr;
v1::Character* Float32Test::character_ = nullptr;

TEST_F(Float32Test, PinsAndCollidersBeyondFloat32AreRefusedNamingTheField) {
  {
    v1::SolveRequest request = Normal();
    v1::Pin* pin = request.mutable_frames(1)->add_pins();
    pin->set_vertex(0);
    pin->mutable_position()->set_x(1e308);
    ExpectRefused(request, "frames[1].pins[0].position.x = 1e+308 is not a finite float32");
  }
  {
    v1::SolveRequest request = Normal();
    v1::Pin* pin = request.mutable_frames(0)->add_pins();
    pin->set_vertex(0);
    pin->mutable_position()->set_z(1e30);  // finite as float32, but no coordinate a solve takes
    ExpectRefused(request, "frames[0].pins[0].position.z = 1e+30 is beyond");
  }
  {
    v1::SolveRequest request = Normal();
    v1::Sphere* sphere = request.add_colliders()->mutable_sphere();
    sphere->mutable_center()->set_y(-100);
    sphere->set_radius(1e200);
    ExpectRefused(request, "colliders[0].sphere.radius = 1e+200 is not a finite float32");
  }
  {
    v1::SolveRequest request = Normal();
    v1::Box* box = request.add_colliders()->mutable_box();
    box->mutable_center()->set_y(-1e3);
    box->mutable_half_extents()->set_x(1e308);
    box->mutable_half_extents()->set_y(1);
    box->mutable_half_extents()->set_z(1);
    ExpectRefused(request, "colliders[0].box.half_extents.x = 1e+308 is not a finite float32");
  }
  {
    v1::SolveRequest request = Normal();
    v1::Sphere* sphere = request.add_colliders()->mutable_sphere();
    sphere->mutable_center()->set_y(-100);
    sphere->set_radius(1);
    request.mutable_frames(1)->add_collider_transforms()->mutable_translation()->set_x(1e300);
    ExpectRefused(request, "frames[1].collider_transforms[0].translation.x = 1e+300 is not a finite float32");
  }
  // A normal request still answers every frame.
  int frames = 0;
  const grpc::Status status = Solve(Normal(), &frames);
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(frames, 2);
}

TEST_F(Float32Test, InbetweensNearTheirNeighboursAreRefusedAtUpload) {
  Client client({server_->address(), std::chrono::seconds(60)});
  for (const double weight : {1e-300, 1.0 - 1e-16}) {
    std::vector<RigTarget> targets(2);
    targets[0].mesh = cylinder_->targets[0];
    targets[1].mesh = cylinder_->targets[1];
    targets[0].inbetweens.push_back({weight, cylinder_->targets[1]});
    std::string message;
    try {
      client.UploadRig(cylinder_->rest, targets);
    } catch (const ClientError& e) {
      message = e.what();
    }
    EXPECT_THAT(message, HasSubstr("header.targets[0] (target '" + targets[0].mesh.name + "'): inbetween_weights[0]"))
        << weight;
    EXPECT_THAT(message, HasSubstr(weight < 0.5 ? "within 1e-06 of 0" : "within 1e-06 of 1")) << message;
  }
  // Two in-betweens 1e-9 apart: a slope of 1e9 between them.
  std::vector<RigTarget> targets(2);
  targets[0].mesh = cylinder_->targets[0];
  targets[1].mesh = cylinder_->targets[1];
  targets[0].inbetweens.push_back({0.5, cylinder_->targets[1]});
  targets[0].inbetweens.push_back({0.5 + 1e-9, cylinder_->rest});
  std::string message;
  try {
    client.UploadRig(cylinder_->rest, targets);
  } catch (const ClientError& e) {
    message = e.what();
  }
  EXPECT_THAT(message, HasSubstr("header.targets[0] (target '" + targets[0].mesh.name + "'): inbetween_weights[1]"));
  EXPECT_THAT(message, HasSubstr("of inbetween_weights[0] = 0.5"));
}

TEST_F(Float32Test, ACombinationsProductPassesTheWeightGuard) {
  Client client({server_->address(), std::chrono::seconds(120)});
  std::vector<RigTarget> targets(3);
  targets[0].mesh = cylinder_->targets[0];
  targets[1].mesh = cylinder_->targets[1];
  targets[2].mesh = cylinder_->targets[1];
  targets[2].mesh.name = "both";
  targets[2].combination = {targets[0].mesh.name, targets[1].mesh.name};
  v1::BuildOptions options;
  options.set_no_target_paths(true);
  const v1::Character rig = client.UploadRig(cylinder_->rest, targets, options, "combination");
  // 100 and 100 pass the plain guard (|w| <= 1000); their product 1e4 does not.
  v1::SolveRequest request = SweepRequest(rig.id(), 1, {100, 100});
  request.mutable_frames(0)->set_weights(0, 100);
  request.mutable_frames(0)->set_weights(1, 100);
  request.mutable_options()->set_linear(true);
  ExpectRefused(request, "frames[0]: combination 'both' has weight 10000 (the product of its drivers' weights)");
  // Within the guard it solves.
  int frames = 0;
  const grpc::Status status = Solve(SweepRequest(rig.id(), 2, {0.5, 0.5}), &frames);
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(frames, 2);
  client.Delete(rig.id());
}

// --- The rest of issue 25: memory every request really holds, the watchdog's reasons, cache files, tokens.

using Clock = std::chrono::steady_clock;

using testing::Metric;

// Waits (a liveness bound, not a timing) until `holds` says yes of the metric.
bool WaitForMetric(int port, const std::string& name, const std::function<bool(double)>& holds) {
  const auto until = Clock::now() + std::chrono::seconds(static_cast<int>(20 * testing::kSlowdown));
  while (!holds(Metric(port, name))) {
    if (Clock::now() > until) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return true;
}

std::string ReadLog(const std::string& path) {
  std::ifstream in(path);
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

// A sweep of linear frames (with normals: large answers), each pinning `pins` vertices where they are: about
// 32 bytes a pin on the wire, several times that parsed.
v1::SolveRequest PinnedSweep(const std::string& id, int frames, int pins) {
  v1::SolveRequest request = SweepRequest(id, frames, {0.5, 0.5});
  request.mutable_options()->set_linear(true);
  request.mutable_options()->set_with_normals(true);
  for (v1::FrameRequest& frame : *request.mutable_frames()) {
    for (int p = 0; p < pins; ++p) {
      v1::Pin* pin = frame.add_pins();
      pin->set_vertex(static_cast<std::uint32_t>(p));
      pin->mutable_position()->set_x(0.5);
      pin->mutable_position()->set_y(0.25);
      pin->mutable_position()->set_z(0.125);
    }
  }
  return request;
}

class RequestMemoryTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    cache_ = new TempDir();
    server_ = new ServerProcess(cache_->File("cache"), {"--workers", "2", "--request-memory-mb", "13", "--metrics",
                                                        "127.0.0.1:0", "--idle-seconds", "30"});
    ASSERT_FALSE(server_->address().empty()) << "the server did not start";
    CylinderRig cylinder;
    Client client({server_->address(), std::chrono::seconds(60)});
    v1::BuildOptions options;
    options.set_no_target_paths(true);
    character_ = new v1::Character(client.Upload(cylinder.rest, cylinder.targets, options, "cylinder"));
  }
  static void TearDownTestSuite() {
    delete server_;
    delete cache_;
    delete character_;
  }
  static double Metric(const std::string& name) { return testing::Metric(server_->metrics_port(), name); }
  static void ExpectServed(const std::string& when) {
    Client client({server_->address(), std::chrono::seconds(20)});
    int frames = 0;
    try {
      frames = client.Solve(SweepRequest(character_->id(), 3, {0.6, 0.3}), [](const v1::SolvedFrame&) {});
    } catch (const ClientError& e) {
      ADD_FAILURE() << when << ": " << e.what();
    }
    EXPECT_EQ(frames, 3) << when;
  }

  static TempDir* cache_;
  static ServerProcess* server_;
  static v1::Character* character_;
};

TempDir* RequestMemoryTest::cache_ = nullptr;
ServerProcess* RequestMemoryTest::server_ = nullptr;
v1::Character* RequestMemoryTest::character_ = nullptr;

// Item 1: four 60 MiB Solve streams held 1.4 GiB against a 64 MiB budget that counted 0.9 MiB of them. Now the
// request's bytes (as received, then parsed) and its converted frames until written are in the budget, with
// its solvers (springblend_solvers, springblend_solver_memory_bytes).
TEST_F(RequestMemoryTest, ASolveRequestsFramesAreInTheBudget) {
  const auto channel = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
  auto stub = v1::SolveService::NewStub(channel);
  // More bytes than the whole budget: refused before it is parsed, with the figures.
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    auto reader = stub->Solve(&context, PinnedSweep(character_->id(), 5000, 100));  // about 16 MB
    v1::SolvedFrame frame;
    int frames = 0;
    while (reader->Read(&frame)) ++frames;
    const grpc::Status status = reader->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr("bytes are free"));
    EXPECT_THAT(status.error_message(), HasSubstr("--request-memory-mb"));
    EXPECT_EQ(frames, 0);
  }
  // One of about 3 MB on the wire (8 parsed, 3 converted) that nobody reads holds its frames in the budget...
  const v1::SolveRequest held = PinnedSweep(character_->id(), 3000, 30);
  ASSERT_GT(held.ByteSizeLong(), 2'500'000u);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(60));
  auto unread = stub->Solve(&context, held);
  // Once converted (before: 3 MB as received, then 11 MB as received and parsed): its 3 MB of frames, its
  // colliders and solvers.
  EXPECT_TRUE(WaitForMetric(server_->metrics_port(), "springblend_request_memory_bytes",
                            [](double bytes) { return bytes >= 3.5e6 && bytes < 7e6; }))
      << Metric("springblend_request_memory_bytes");
  EXPECT_GE(Metric("springblend_solvers"), 1);
  // ... so a second one does not fit beside it (13 MiB: its bytes, parsed, on top of the first one's frames).
  {
    grpc::ClientContext second;
    second.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    auto reader = stub->Solve(&second, held);
    v1::SolvedFrame frame;
    while (reader->Read(&frame)) {
    }
    const grpc::Status status = reader->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr("this request needs"));
  }
  ExpectServed("with a stream of 3000 unread frames open");
  // Read at last, it answers every frame, and everything it held returns to the budget.
  v1::SolvedFrame frame;
  int frames = 0;
  while (unread->Read(&frame)) ++frames;
  const grpc::Status status = unread->Finish();
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(frames, 3000);
  EXPECT_TRUE(WaitForMetric(server_->metrics_port(), "springblend_request_memory_bytes",
                            [](double bytes) { return bytes == 0; }))
      << Metric("springblend_request_memory_bytes");
  EXPECT_EQ(Metric("springblend_solvers"), 0);
  EXPECT_EQ(Metric("springblend_solver_memory_bytes"), 0);
}

// Item 2: a face session held 64-70 MiB against 6.6 MiB counted. A session's Solver is counted by its factor's
// size (known from the rig's analysis), and the gauges show it while the session is open.
TEST_F(RequestMemoryTest, ASessionsSolverIsCountedFromItsFactor) {
  Client client({server_->address(), std::chrono::seconds(30)});
  v1::InteractiveStart start;
  start.set_character_id(character_->id());
  auto session = client.StartInteractive(start);
  v1::FrameRequest frame;
  frame.add_weights(0.5);
  frame.add_weights(0.2);
  ASSERT_TRUE(session->Send(frame));
  v1::SolvedFrame answer;
  ASSERT_TRUE(session->Next(&answer));
  // The cylinder's factor has 220k entries: at least 1.7 MB after its first frame (8 bytes each).
  EXPECT_GE(Metric("springblend_solver_memory_bytes"), 220'000 * 8.0);
  EXPECT_EQ(Metric("springblend_solvers"), 1);
  EXPECT_GE(Metric("springblend_request_memory_bytes"), Metric("springblend_solver_memory_bytes"));
  session->Close();
  while (session->Next(&answer)) {
  }
  EXPECT_NO_THROW(session->Finish());
  EXPECT_TRUE(WaitForMetric(server_->metrics_port(), "springblend_solvers", [](double n) { return n == 0; }));
  EXPECT_TRUE(WaitForMetric(server_->metrics_port(), "springblend_request_memory_bytes",
                            [](double bytes) { return bytes == 0; }));
}

// A budget smaller than one session's Solver refuses the session at its start, naming the budget; a linear
// session (no factor) still fits.
TEST(RequestMemory, ASessionWhoseSolverDoesNotFitIsRefused) {
  TempDir dir;
  ServerProcess server(dir.File("cache"), {"--workers", "1", "--request-memory-mb", "2"});
  ASSERT_FALSE(server.address().empty());
  CylinderRig cylinder;
  Client client({server.address(), std::chrono::seconds(30)});
  v1::BuildOptions options;
  options.set_no_target_paths(true);
  const v1::Character character = client.Upload(cylinder.rest, cylinder.targets, options, "cylinder");
  v1::FrameRequest frame;
  frame.add_weights(0.5);
  frame.add_weights(0.2);
  v1::SolvedFrame answer;
  {
    v1::InteractiveStart start;
    start.set_character_id(character.id());
    auto session = client.StartInteractive(start);
    session->Send(frame);
    EXPECT_FALSE(session->Next(&answer));
    try {
      session->Finish();
      ADD_FAILURE() << "the session was served";
    } catch (const ClientError& e) {
      EXPECT_EQ(e.code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << e.what();
      EXPECT_THAT(e.what(), HasSubstr("--request-memory-mb"));
    }
  }
  v1::InteractiveStart linear;
  linear.set_character_id(character.id());
  linear.mutable_options()->set_linear(true);
  auto session = client.StartInteractive(linear);
  ASSERT_TRUE(session->Send(frame));
  EXPECT_TRUE(session->Next(&answer));
  session->Close();
  while (session->Next(&answer)) {
  }
  EXPECT_NO_THROW(session->Finish());
}

// Item 7: the idle timeout counted the server's own work: a session waiting for its setup (here the face's rig
// rebuilt from the cache directory and its first frame, far longer than --idle-seconds 0.1) was cancelled as
// idle. Once answered and left alone it is, with the watchdog's reason as the message.
TEST(Watchdog, ASessionWaitingForTheServerIsNotIdle) {
  TempDir dir;
  std::string id;
  {
    ServerProcess first(dir.File("cache"), {"--workers", "1"});
    ASSERT_FALSE(first.address().empty());
    Client client({first.address(), std::chrono::seconds(120)});
    v1::BuildOptions options;
    options.set_no_target_paths(true);
    id = client.Upload(LoadMesh(testing::DataPath("face/generic_neutral_mesh.obj")),
                       {LoadMesh(testing::DataPath("face/jawOpen.obj"))}, options, "face")
             .id();
  }
  ServerProcess server(dir.File("cache"), {"--workers", "1", "--idle-seconds", "0.1"});
  ASSERT_FALSE(server.address().empty());
  const auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto stub = v1::SolveService::NewStub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(static_cast<int>(120 * testing::kSlowdown)));
  auto session = stub->Interactive(&context);
  v1::InteractiveRequest start;
  start.mutable_start()->set_character_id(id);
  ASSERT_TRUE(session->Write(start));
  v1::InteractiveRequest frame;
  frame.mutable_frame()->add_weights(0.5);
  ASSERT_TRUE(session->Write(frame));
  const auto began = Clock::now();
  int answers = 0;
  v1::SolvedFrame answer;
  while (session->Read(&answer)) ++answers;
  const grpc::Status status = session->Finish();
  EXPECT_EQ(answers, 1) << "the session was cut off while the server rebuilt its character: "
                        << status.error_message();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED);
  EXPECT_THAT(status.error_message(), HasSubstr("idle for longer than --idle-seconds"));
  EXPECT_LT(Clock::now() - began, std::chrono::seconds(static_cast<int>(60 * testing::kSlowdown)));
}

// Item 7: tokens: the scheme is case-insensitive (RFC 9110), another scheme is refused as missing.
TEST(Tokens, TheBearerSchemeIsCaseInsensitive) {
  TempDir dir;
  ServerProcess server(dir.File("cache"), {"--workers", "1", "--token", "s3cret"});
  ASSERT_FALSE(server.address().empty());
  const auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto stub = v1::CharacterService::NewStub(channel);
  const auto list = [&](const std::string& header) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    context.AddMetadata("authorization", header);
    v1::ListCharactersResponse response;
    return stub->ListCharacters(&context, {}, &response).error_code();
  };
  for (const char* scheme : {"Bearer", "bearer", "BEARER", "bEaReR"}) {
    EXPECT_EQ(list(std::string(scheme) + " s3cret"), grpc::StatusCode::OK) << scheme;
  }
  EXPECT_EQ(list("Basic s3cret"), grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_EQ(list("bearer wrong"), grpc::StatusCode::UNAUTHENTICATED);
}

// Item 7: a message names its field once ("colliders[0]: colliders[0].mesh_obj: ..." before).
TEST_F(Float32Test, AColliderIsNamedOnceInItsMessage) {
  v1::SolveRequest request = Normal();
  request.add_colliders()->set_mesh_obj("v 0 0 0\nv 1 0 0\nf 1 2 3\n");
  const grpc::Status status = Solve(request);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  const std::string& message = status.error_message();
  ASSERT_THAT(message, HasSubstr("colliders[0]"));
  EXPECT_EQ(message.find("colliders[0]"), message.rfind("colliders[0]")) << message;
}

// Item 7: cache files are read only when regular: a FIFO named like one held the metadata pool for good, and an
// empty directory named like one was removed. Both are left alone, said in the log, and the server serves on.
TEST(CacheFiles, OnlyRegularFilesAreReadOrRemoved) {
  TempDir dir;
  const std::filesystem::path cache = dir.File("cache");
  std::filesystem::create_directories(cache);
  const std::string fifo_id(64, 'a'), directory_id(64, 'b');
  ASSERT_EQ(mkfifo((cache / (fifo_id + ".sbchar")).c_str(), 0644), 0);
  std::filesystem::create_directory(cache / (directory_id + ".sbchar"));
  const std::string log = dir.File("server.log");
  ServerProcess server(cache.string(), {"--workers", "1", "--metadata-workers", "1"}, log);
  ASSERT_FALSE(server.address().empty());
  Client client({server.address(), std::chrono::seconds(static_cast<int>(10 * testing::kSlowdown))});
  for (int i = 0; i < 2; ++i) {  // one metadata worker: a blocked first Get would time out the second
    EXPECT_EQ(testing::StatusOf([&] { client.Get(fifo_id); }), grpc::StatusCode::NOT_FOUND);
  }
  EXPECT_EQ(testing::StatusOf([&] { client.Get(directory_id); }), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(testing::StatusOf([&] { client.Delete(directory_id); }), grpc::StatusCode::NOT_FOUND);
  EXPECT_TRUE(client.List().empty());
  EXPECT_TRUE(std::filesystem::is_directory(cache / (directory_id + ".sbchar")));
  EXPECT_TRUE(std::filesystem::is_fifo(cache / (fifo_id + ".sbchar")));
  EXPECT_TRUE(client.Healthy());
  EXPECT_THAT(ReadLog(log), HasSubstr("is not a regular file"));
}

// A directory this process cannot write: root writes through any mode bits, so then one of /proc's.
std::string UnwritableDirectory(const TempDir& dir) {
  if (geteuid() == 0) return "/proc/self/fdinfo";
  const std::string path = dir.File("read-only");
  std::filesystem::create_directories(path);
  chmod(path.c_str(), 0555);
  return path;
}

// Item 7: a read-only cache directory failed every write silently. Start-up warns, each failed write is logged
// and counted, and the characters are served from memory.
TEST(CacheFiles, AReadOnlyCacheDirectoryIsSaidAndCounted) {
  TempDir dir;
  const std::string log = dir.File("server.log");
  ServerProcess server(UnwritableDirectory(dir), {"--workers", "1", "--metrics", "127.0.0.1:0"}, log);
  ASSERT_FALSE(server.address().empty());
  EXPECT_THAT(ReadLog(log), HasSubstr("is not writable"));
  CylinderRig cylinder;
  Client client({server.address(), std::chrono::seconds(60)});
  v1::BuildOptions options;
  options.set_no_target_paths(true);
  const v1::Character character = client.Upload(cylinder.rest, cylinder.targets, options, "cylinder");
  // Hardening IV (items 6 and 14): the upload's answer, and the character's description, say it was not kept.
  EXPECT_THAT(::testing::PrintToString(character.summary().notes()), HasSubstr("not persisted: its cache file"));
  EXPECT_THAT(::testing::PrintToString(client.Get(character.id()).summary().notes()),
              HasSubstr("served from this server's memory only"));
  EXPECT_EQ(client.Solve(SweepRequest(character.id(), 2, {0.5, 0.5}), [](const v1::SolvedFrame&) {}), 2);
  EXPECT_GE(Metric(server.metrics_port(), "springblend_cache_write_failures_total"), 1);
  EXPECT_THAT(ReadLog(log), HasSubstr("not written"));
}

}  // namespace
}  // namespace springblend
