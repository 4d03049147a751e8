// Hardening III against a real server: ports that are taken (no SO_REUSEPORT), a tokens file without tokens,
// flags out of range, and values finite as doubles but not as the float32 the answers carry (pins, colliders,
// in-between weights, combination products). Each refusal names the flag or the field; a normal client is
// served meanwhile.
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

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

struct ServerRun {
  int exit_code = -1;
  std::string output;  // stdout and stderr
};

// Runs springblend-server with these arguments; one that starts is stopped by `timeout` (exit code 124).
ServerRun RunServer(const TempDir& dir, const std::vector<std::string>& arguments) {
  std::string command = "timeout 10 " + std::string(SPRINGBLEND_SERVER) + " --cache-dir " + dir.File("cache");
  for (const auto& a : arguments) command += " '" + a + "'";
  command += " 2>&1 </dev/null";
  ServerRun run;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return run;
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) run.output.append(buffer.data(), n);
  const int status = pclose(pipe);
  run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return run;
}

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
    EXPECT_THAT(message, HasSubstr("header.targets[0].inbetween_weights[0] (target '" + targets[0].mesh.name + "')"))
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
  EXPECT_THAT(message, HasSubstr("header.targets[0].inbetween_weights[1]"));
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

}  // namespace
}  // namespace springblend
