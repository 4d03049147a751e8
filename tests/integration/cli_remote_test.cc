// The remote commands of the springblend CLI (upload, solve, list, delete, health) against a real server, a
// closed port and a port that accepts connections but never answers: --timeout, $SPRINGBLEND_SERVER, and
// failures told by status name, call and hint.
#include <arpa/inet.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <grpcpp/grpcpp.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <set>
#include <map>
#include <filesystem>
#include <fstream>
#include <thread>

#include "integration/cli_process.h"
#include "integration/server_process.h"
#include "springblend/point_cache.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using testing::CliRun;
using testing::DataPath;
using testing::RunCli;
using testing::ServerProcess;
using testing::TempDir;

const std::string kCylinder = " --rest " + DataPath("cylinder/cylinder.obj") + " --target " +
                              DataPath("cylinder/poses-2_cylinder-1.obj") + " --target " +
                              DataPath("cylinder/poses-2_cylinder-3.obj");

// A loopback port that completes TCP connections (the kernel's backlog) but never speaks HTTP/2: every call
// to it waits until its deadline, as behind a firewall that swallows packets after the handshake.
class SilentPort {
 public:
  SilentPort() {
    fd_ = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t length = sizeof(address);
    EXPECT_EQ(bind(fd_, reinterpret_cast<sockaddr*>(&address), sizeof(address)), 0);
    EXPECT_EQ(listen(fd_, 64), 0);
    EXPECT_EQ(getsockname(fd_, reinterpret_cast<sockaddr*>(&address), &length), 0);
    address_ = "127.0.0.1:" + std::to_string(ntohs(address.sin_port));
  }
  ~SilentPort() { close(fd_); }
  const std::string& address() const { return address_; }

 private:
  int fd_ = -1;
  std::string address_;
};

// A loopback port nothing listens on (bound, then closed).
std::string ClosedPort() {
  SilentPort port;
  return port.address();
}

double SecondsOf(const std::function<void()>& run) {
  const auto start = std::chrono::steady_clock::now();
  run();
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

class CliRemoteTest : public ::testing::Test {
 protected:
  TempDir dir_, cache_;
};

TEST_F(CliRemoteTest, SpringblendServerIsTheDefaultAddressOfEveryCommand) {
  ServerProcess server(cache_.path().string());
  ASSERT_FALSE(server.address().empty());
  const std::string env = "SPRINGBLEND_SERVER=" + server.address();
  const CliRun upload = RunCli("upload" + kCylinder, dir_, env);
  ASSERT_EQ(upload.exit_code, 0) << upload.stderr_text;
  const std::string id = upload.lines.at(0)["id"];
  const CliRun list = RunCli("list", dir_, env);
  ASSERT_EQ(list.exit_code, 0) << list.stderr_text;
  ASSERT_EQ(list.lines.size(), 1u);
  EXPECT_EQ(list.lines[0]["id"], id);
  const CliRun solve =
      RunCli("solve --character " + id + " --weights 0.5,0.5 --timeout 60 --out " + dir_.File("frames"), dir_, env);
  EXPECT_EQ(solve.exit_code, 0) << solve.stderr_text;
  // Each target's path, and the weights where it is not certified (pairs of weights).
  const CliRun described = RunCli("describe --character " + id, dir_, env);
  ASSERT_EQ(described.exit_code, 0) << described.stderr_text;
  const nlohmann::json& paths = described.lines.at(0)["paths"];
  EXPECT_EQ(paths.size(), described.lines.at(0)["targets"].size());
  for (const nlohmann::json& p : paths) {
    EXPECT_GT(p["samples"].get<int>(), 0);
    EXPECT_GT(p["ms"].get<double>(), 0.0);
    EXPECT_LE(p["local_checks"].get<int>(), p["checks"].get<int>());
    for (const nlohmann::json& range : p["uncertified_ranges"]) {
      ASSERT_EQ(range.size(), 2u);
      EXPECT_LT(range[0].get<double>(), range[1].get<double>());
    }
  }
  const CliRun health = RunCli("health --timeout 10", dir_, env);
  EXPECT_EQ(health.exit_code, 0) << health.stderr_text;
  EXPECT_EQ(health.lines.at(0)["status"], "SERVING");
  EXPECT_EQ(health.lines.at(0)["server"], server.address());
  // --server wins over the variable.
  const CliRun elsewhere = RunCli("list --server " + ClosedPort(), dir_, env);
  EXPECT_EQ(elsewhere.exit_code, 4);
  EXPECT_THAT(elsewhere.stderr_text, HasSubstr("(--server)"));
  EXPECT_EQ(RunCli("delete --character " + id, dir_, env).exit_code, 0);
}

TEST_F(CliRemoteTest, AnUnreachableServerIsSaidToBeUnreachableByName) {
  const std::string address = ClosedPort();
  const CliRun health = RunCli("health --server " + address, dir_);
  EXPECT_EQ(health.exit_code, 4);
  ASSERT_EQ(health.lines.size(), 1u);
  EXPECT_EQ(health.lines[0]["status"], "UNREACHABLE");
  EXPECT_EQ(health.lines[0]["code"], "UNAVAILABLE");
  EXPECT_THAT(health.stderr_text, Not(HasSubstr("NOT_SERVING")));
  EXPECT_THAT(health.stderr_text, HasSubstr("springblend health: UNAVAILABLE: cannot reach a springblend server at " +
                                            address));
  for (const std::string& command : std::vector<std::string>{"list", "upload" + kCylinder}) {
    const CliRun run = RunCli(command + " --server " + address, dir_);
    EXPECT_EQ(run.exit_code, 4) << command;
    EXPECT_THAT(run.stderr_text, HasSubstr(": UNAVAILABLE: cannot reach")) << command;
    EXPECT_THAT(run.stderr_text, HasSubstr("$SPRINGBLEND_SERVER")) << command;
    EXPECT_THAT(run.stderr_text, Not(HasSubstr(" 14"))) << command;
  }
  // Without --server nor the variable, the message says the default was used.
  const CliRun fallback = RunCli("list", dir_, "SPRINGBLEND_SERVER=");
  if (fallback.exit_code != 0) {
    EXPECT_THAT(fallback.stderr_text, HasSubstr("127.0.0.1:50051 (the default)"));
  }
}

TEST_F(CliRemoteTest, TimeoutBoundsEveryCommandAndTheMessageNamesTheCallAndTheFix) {
  SilentPort silent;
  const std::string server = " --server " + silent.address() + " --timeout 1";
  const std::vector<std::pair<std::string, std::string>> commands = {
      {"list", "list"},
      {"delete --character " + std::string(64, 'a'), "delete"},
      {"upload" + kCylinder, "upload"},
      {"solve --character " + std::string(64, 'a') + " --weights 0.5,0.5 --out " + dir_.File("never"), "get"},
      {"health", "health"}};
  for (const auto& [command, call] : commands) {
    CliRun run;
    const double seconds = SecondsOf([&] { run = RunCli(command + server, dir_); });
    EXPECT_EQ(run.exit_code, 4) << command << ": " << run.stderr_text;
    EXPECT_LT(seconds, 10.0) << command;
    EXPECT_THAT(run.stderr_text, HasSubstr("DEADLINE_EXCEEDED: " + call)) << command;
    EXPECT_THAT(run.stderr_text, HasSubstr("did not finish within --timeout 1 s")) << command;
    EXPECT_THAT(run.stderr_text, HasSubstr("raise --timeout")) << command;
  }
  const CliRun upload = RunCli("upload" + kCylinder + server, dir_);
  EXPECT_THAT(upload.stderr_text, HasSubstr("leave it out: upload has no time limit by default"));
  const CliRun health = RunCli("health" + server, dir_);
  EXPECT_EQ(health.lines.at(0)["status"], "UNREACHABLE");
  // Health's default limit is 5 s, and the message says it was the default.
  const CliRun by_default = RunCli("health --server " + silent.address(), dir_);
  EXPECT_EQ(by_default.exit_code, 4);
  EXPECT_THAT(by_default.stderr_text, HasSubstr("within 5 s (the default limit of health)"));
  EXPECT_THAT(by_default.stderr_text, HasSubstr("pass --timeout SECONDS"));
}

TEST_F(CliRemoteTest, ASolveOverItsTimeoutSaysHowManyFramesArrived) {
  ServerProcess server(cache_.path().string(), {"--workers", "1"});
  ASSERT_FALSE(server.address().empty());
  const std::string remote = " --server " + server.address();
  const CliRun upload = RunCli("upload" + kCylinder + remote + " --no-target-paths", dir_);
  ASSERT_EQ(upload.exit_code, 0) << upload.stderr_text;
  const std::string id = upload.lines.at(0)["id"];
  // 5000 frames on one worker take far longer than a second.
  const CliRun solve = RunCli("solve --character " + id + " --weights 1,1 --sweep 5000 --timeout 1 --out " +
                                  dir_.File("sweep") + remote,
                              dir_);
  EXPECT_EQ(solve.exit_code, 4) << solve.stderr_text;
  EXPECT_THAT(solve.stderr_text, HasSubstr("springblend solve: DEADLINE_EXCEEDED: solve did not finish within "
                                           "--timeout 1 s"));
  EXPECT_THAT(solve.stderr_text, HasSubstr("of 5000 frames arrived"));
  EXPECT_THAT(solve.stderr_text, HasSubstr("leave it out: solve has no time limit by default"));
  // The server is fine afterwards.
  EXPECT_EQ(RunCli("health" + remote, dir_).exit_code, 0);
}

// The face's build takes minutes (its five expressions with the densest paths): the upload prints its progress on
// stderr as it goes, and, given --timeout, gives up on time with the call named (the server then stops the build
// nobody waits for).
TEST_F(CliRemoteTest, UploadShowsTheBuildsProgressAndHonoursItsTimeout) {
  ServerProcess server(cache_.path().string(), {"--metrics", "127.0.0.1:0"});
  ASSERT_FALSE(server.address().empty());
  const std::string remote = " --server " + server.address();
  std::string face = " --path-intervals 128 --rest " + DataPath("face/generic_neutral_mesh.obj") + " --target";
  for (const char* name : {"jawOpen", "mouthClose", "mouthFunnel", "mouthSmile_L", "mouthStretch_L"}) {
    face += ' ';
    face += DataPath(std::string("face/") + name + ".obj");
  }
  CliRun upload;
  const double seconds = SecondsOf([&] { upload = RunCli("upload" + face + " --timeout 8" + remote, dir_); });
  EXPECT_EQ(upload.exit_code, 4) << upload.stderr_text;
  EXPECT_LT(seconds, 20.0);
  EXPECT_THAT(upload.stderr_text, HasSubstr("DEADLINE_EXCEEDED: upload did not finish within --timeout 8 s"));
  EXPECT_THAT(upload.stderr_text, ::testing::ContainsRegex("building [0-9a-f]{12}: [a-z]+"));
  EXPECT_TRUE(upload.lines.empty()) << "an upload that gave up printed a character";
  // Nobody waits for the build any more: it stops.
  const auto gave_up = std::chrono::steady_clock::now();
  const auto busy = [&] {
    const std::string text = testing::HttpGet(server.metrics_port(), "/metrics");
    return text.find("\nspringblend_build_workers_busy 0\n") == std::string::npos;
  };
  while (busy() && std::chrono::steady_clock::now() - gave_up < std::chrono::seconds(10)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_FALSE(busy()) << "the abandoned build still runs";
}

TEST_F(CliRemoteTest, RefusalsAreNamedWithAHint) {
  ServerProcess server(cache_.path().string(), {"--token", "cli-secret"});
  ASSERT_FALSE(server.address().empty());
  const std::string remote = " --server " + server.address();
  const CliRun anonymous = RunCli("list" + remote, dir_, "SPRINGBLEND_TOKEN=");
  EXPECT_EQ(anonymous.exit_code, 2);
  EXPECT_THAT(anonymous.stderr_text, HasSubstr("springblend list: UNAUTHENTICATED: "));
  EXPECT_THAT(anonymous.stderr_text, HasSubstr("pass --token TOKEN or set $SPRINGBLEND_TOKEN"));
  const CliRun wrong = RunCli("list --token nope" + remote, dir_);
  EXPECT_EQ(wrong.exit_code, 2);
  EXPECT_THAT(wrong.stderr_text, HasSubstr("does not accept this token"));
  const CliRun unknown = RunCli("delete --character " + std::string(64, 'b') + remote, dir_,
                                "SPRINGBLEND_TOKEN=cli-secret");
  EXPECT_EQ(unknown.exit_code, 2);
  EXPECT_THAT(unknown.stderr_text, HasSubstr("springblend delete: NOT_FOUND: "));
  EXPECT_THAT(unknown.stderr_text, HasSubstr("springblend list shows"));
  // Health needs no token.
  EXPECT_EQ(RunCli("health" + remote, dir_, "SPRINGBLEND_TOKEN=").exit_code, 0);
  // A CA file that is not there is named.
  const CliRun no_ca = RunCli("list --tls-ca " + dir_.File("missing-ca.pem") + remote, dir_);
  EXPECT_EQ(no_ca.exit_code, 2);
  EXPECT_THAT(no_ca.stderr_text, HasSubstr("--tls-ca: cannot open " + dir_.File("missing-ca.pem")));
}

// The pipeline habits of issue-free shots: an upload whose targets move every vertex is said to be floating and
// refuses colliders; the same meshes uploaded with --hold-outer-rim (and the upload's other rig options) take
// them; weights go by target name; the point cache starts at the shot's first frame.
TEST_F(CliRemoteTest, AHeldRimUploadTakesCollidersAndNamedWeightsIntoAShotsPointCache) {
  ServerProcess server(cache_.path().string());
  ASSERT_FALSE(server.address().empty());
  const std::string remote = " --server " + server.address() + " --timeout 120";
  const std::string meshes = " --rest " + DataPath("cylinder/cylinder.obj") + " --target " +
                             DataPath("cylinder/poses-1_cylinder-2.obj") + " --no-anchor --no-target-paths";
  const CliRun floating = RunCli("upload" + meshes + remote, dir_);
  ASSERT_EQ(floating.exit_code, 0) << floating.stderr_text;
  EXPECT_EQ(floating.lines.at(0)["boundary_mode"], "floating");
  EXPECT_THAT(floating.stderr_text, HasSubstr("springblend upload: note: the rig is floating"));
  const std::string collider = " --collider sphere:0,0.75,0.75,0.3";
  const CliRun refused = RunCli("solve --character " + floating.lines.at(0)["id"].get<std::string>() +
                                    " --weights poses-1_cylinder-2=1" + collider + " --out " + dir_.File("no") + remote,
                                dir_);
  EXPECT_EQ(refused.exit_code, 2);
  EXPECT_THAT(refused.stderr_text, HasSubstr("--hold-outer-rim"));

  const CliRun too_coarse = RunCli("upload" + meshes + " --path-intervals 3" + remote, dir_);
  EXPECT_EQ(too_coarse.exit_code, 2);
  EXPECT_THAT(too_coarse.stderr_text, HasSubstr("--path-intervals"));
  const CliRun held =
      RunCli("upload" + meshes + " --hold-outer-rim --static-tolerance 1e-5 --bending-stiffness 0.8" + remote, dir_);
  ASSERT_EQ(held.exit_code, 0) << held.stderr_text;
  EXPECT_EQ(held.lines.at(0)["boundary_mode"], "fixed_vertices");
  EXPECT_GT(held.lines.at(0)["rim_vertices"].get<int>(), 0);
  EXPECT_THAT(held.stderr_text, Not(HasSubstr("floating")));
  EXPECT_NE(held.lines.at(0)["id"], floating.lines.at(0)["id"]);
  const std::string shot = dir_.File("shot.pc2");
  const CliRun solved = RunCli("solve --character " + held.lines.at(0)["id"].get<std::string>() +
                                   " --weights poses-1_cylinder-2=1 --sweep 3 --start-frame 1001" + collider +
                                   " --out " + shot + remote,
                               dir_);
  ASSERT_EQ(solved.exit_code, 0) << solved.stderr_text;
  ASSERT_EQ(solved.lines.size(), 3u);
  for (const auto& line : solved.lines) EXPECT_TRUE(line["converged"].get<bool>()) << line.dump();
  const PointCache cache = ReadPointCache(shot);
  EXPECT_EQ(cache.start_frame, 1001.0f);
  EXPECT_EQ(cache.samples.size(), 3u);
  const CliRun unknown = RunCli("solve --character " + held.lines.at(0)["id"].get<std::string>() +
                                    " --weights jawOpen=1 --out " + dir_.File("unknown") + remote,
                                dir_);
  EXPECT_EQ(unknown.exit_code, 2);
  EXPECT_THAT(unknown.stderr_text, HasSubstr("'jawOpen' is not a target of this character (targets: poses-1_cylinder-2)"));
}

// A character is named as the logs and `list` show it: 12 or more hex digits of its id, or its name; describe
// shows one character whatever names it; an unknown or ambiguous name is refused, saying which.
TEST_F(CliRemoteTest, CharactersAreNamedByIdPrefixOrNameAndDescribed) {
  ServerProcess server(cache_.path().string());
  ASSERT_FALSE(server.address().empty());
  const std::string remote = " --server " + server.address() + " --timeout 120";
  const CliRun upload = RunCli("upload" + kCylinder + " --name arm --no-target-paths" + remote, dir_);
  ASSERT_EQ(upload.exit_code, 0) << upload.stderr_text;
  const std::string id = upload.lines.at(0)["id"];
  for (const std::string& given : {id, id.substr(0, 12), id.substr(0, 40), std::string("arm")}) {
    const CliRun described = RunCli("describe --character " + given + remote, dir_);
    ASSERT_EQ(described.exit_code, 0) << given << ": " << described.stderr_text;
    const nlohmann::json& d = described.lines.at(0);
    EXPECT_EQ(d["id"], id) << given;
    EXPECT_EQ(d["name"], "arm");
    EXPECT_EQ(d["state"], "READY");
    EXPECT_EQ(d["targets"], nlohmann::json::array({"poses-2_cylinder-1", "poses-2_cylinder-3"}));
    EXPECT_EQ(d["surface_vertices"], 420);
    EXPECT_EQ(d["faces"], 800);
    EXPECT_FALSE(d["interior"].get<std::string>().empty());
    EXPECT_GT(d["precompute_ms"].get<double>(), 0.0);
    EXPECT_EQ(d["paths"], nlohmann::json::array()) << "uploaded without target paths";
  }
  const CliRun solved = RunCli("solve --character " + id.substr(0, 12) + " --weights 0.5,0.5 --out " +
                                   dir_.File("frames") + remote,
                               dir_);
  EXPECT_EQ(solved.exit_code, 0) << solved.stderr_text;
  EXPECT_EQ(solved.lines.size(), 1u);

  const CliRun short_prefix = RunCli("describe --character " + id.substr(0, 8) + remote, dir_);
  EXPECT_EQ(short_prefix.exit_code, 2);
  EXPECT_THAT(short_prefix.stderr_text, HasSubstr("--character '" + id.substr(0, 8) + "': no character on the server has this name"));
  EXPECT_THAT(short_prefix.stderr_text, HasSubstr("12 or more of its hex digits"));
  // Another character with the same name: the name no longer says which.
  const CliRun other = RunCli("upload --rest " + DataPath("cylinder/cylinder.obj") + " --target " +
                                  DataPath("cylinder/poses-2_cylinder-2.obj") + " --name arm --no-target-paths" + remote,
                              dir_);
  ASSERT_EQ(other.exit_code, 0) << other.stderr_text;
  const CliRun ambiguous = RunCli("describe --character arm" + remote, dir_);
  EXPECT_EQ(ambiguous.exit_code, 2);
  EXPECT_THAT(ambiguous.stderr_text, HasSubstr("--character 'arm' names 2 characters"));
  const CliRun removed = RunCli("delete --character " + id.substr(0, 12) + remote, dir_);
  ASSERT_EQ(removed.exit_code, 0) << removed.stderr_text;
  EXPECT_EQ(removed.lines.at(0)["deleted"], id);
  EXPECT_EQ(RunCli("describe --character arm" + remote, dir_).lines.at(0)["id"], other.lines.at(0)["id"]);
}

// bake-rig against a server's character (frames solved there, its combination's drivers from the rig file) bakes
// the rig the local bake does: the same in-betweens and correctives, the same shapes to float32.
TEST_F(CliRemoteTest, ABakeOfAServersCharacterIsTheLocalBake) {
  ServerProcess server(cache_.path().string());
  ASSERT_FALSE(server.address().empty());
  const std::string remote = " --server " + server.address() + " --timeout 120";
  const std::string rig = DataPath("cylinder/rig.json");
  const CliRun upload = RunCli("upload --rig " + rig + " --name bakeable" + remote, dir_);
  ASSERT_EQ(upload.exit_code, 0) << upload.stderr_text;
  const std::string options = " --samples 8 --inbetweens 2 --rig " + rig;
  const CliRun there =
      RunCli("bake-rig --character bakeable" + options + " --out " + dir_.File("remote") + remote, dir_);
  ASSERT_EQ(there.exit_code, 0) << there.stderr_text;
  const CliRun here = RunCli("bake-rig" + options + " --out " + dir_.File("local"), dir_);
  ASSERT_EQ(here.exit_code, 0) << here.stderr_text;
  const nlohmann::json& a = there.lines.at(0);
  const nlohmann::json& b = here.lines.at(0);
  EXPECT_EQ(a["frames"], b["frames"]);
  ASSERT_EQ(a["targets"].size(), 2u);
  for (size_t t = 0; t < 2; ++t) EXPECT_EQ(a["targets"][t]["inbetweens"], b["targets"][t]["inbetweens"]) << t;
  ASSERT_EQ(a["combinations"].size(), b["combinations"].size());
  EXPECT_EQ(a["combinations"][0]["drivers"], nlohmann::json::array({"bend", "twist"}));
  const double diagonal = BoundingBoxDiagonal(LoadMesh(DataPath("cylinder/cylinder.obj")).vertices);
  for (const auto& entry : std::filesystem::directory_iterator(dir_.File("local"))) {
    if (entry.path().extension() != ".obj") continue;
    const std::string name = entry.path().filename().string();
    EXPECT_LE(testing::MaxDistance(LoadMesh(entry.path().string()).vertices,
                                   LoadMesh(dir_.File("remote/" + name)).vertices),
              1e-6 * diagonal)
        << name;
  }
  const CliRun both = RunCli("bake-rig --character bakeable --rest " + DataPath("cylinder/cylinder.obj") + " --out " +
                                 dir_.File("x") + remote,
                             dir_);
  EXPECT_EQ(both.exit_code, 2);
  EXPECT_THAT(both.stderr_text, HasSubstr("drop --rest and --target"));
  const CliRun unknown = RunCli("bake-rig --character nobody --out " + dir_.File("x") + remote, dir_);
  EXPECT_EQ(unknown.exit_code, 2);
  EXPECT_THAT(unknown.stderr_text, HasSubstr("--character 'nobody': no character on the server has this name"));
}

// --log-format json: every line the server writes is one JSON object, and every call leaves one access line
// (method, character, frames, status, ms, peer, request id). A call's request id is the client's x-request-id,
// else a new one, and comes back in the response's initial metadata.
TEST_F(CliRemoteTest, JsonLogsHaveOneAccessLinePerCallWithItsRequestId) {
  const std::string log = dir_.File("server.log");
  std::string echoed, made;
  {
    ServerProcess server(cache_.path().string(), {"--log-format", "json"}, log);
    ASSERT_FALSE(server.address().empty());
    const std::string remote = " --server " + server.address() + " --timeout 120";
    const CliRun upload = RunCli("upload" + kCylinder + " --name arm --no-target-paths" + remote, dir_);
    ASSERT_EQ(upload.exit_code, 0) << upload.stderr_text;
    const std::string id = upload.lines.at(0)["id"];
    ASSERT_EQ(RunCli("solve --character " + id + " --sweep 2 --weights 0.5,0.5 --out " + dir_.File("f") + remote, dir_)
                  .exit_code,
              0);
    EXPECT_EQ(RunCli("describe --character " + std::string(64, 'c') + remote, dir_).exit_code, 2);  // NOT_FOUND
    auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
    auto stub = v1::CharacterService::NewStub(channel);
    for (const bool given : {true, false}) {
      grpc::ClientContext context;
      if (given) context.AddMetadata("x-request-id", "trace-abc-123");
      v1::ListCharactersResponse response;
      ASSERT_TRUE(stub->ListCharacters(&context, v1::ListCharactersRequest(), &response).ok());
      const auto& metadata = context.GetServerInitialMetadata();
      const auto found = metadata.find("x-request-id");
      ASSERT_NE(found, metadata.end());
      (given ? echoed : made) = std::string(found->second.data(), found->second.size());
    }
  }
  EXPECT_EQ(echoed, "trace-abc-123");
  EXPECT_EQ(made.size(), 16u);
  std::ifstream in(log);
  std::map<std::string, std::vector<nlohmann::json>> access;  // by method
  int lines = 0;
  for (std::string line; std::getline(in, line);) {
    ++lines;
    nlohmann::json entry;
    ASSERT_NO_THROW(entry = nlohmann::json::parse(line)) << line;
    EXPECT_TRUE(entry.contains("time") && entry.contains("level")) << line;
    if (entry.value("access", false)) {
      access[entry["method"]].push_back(entry);
    } else {
      EXPECT_TRUE(entry["message"].is_string()) << line;
    }
  }
  EXPECT_GT(lines, 5);
  ASSERT_EQ(access["UploadCharacter"].size(), 1u);
  EXPECT_EQ(access["UploadCharacter"][0]["status"], "OK");
  EXPECT_EQ(access["UploadCharacter"][0]["character"].get<std::string>().size(), 12u);
  ASSERT_EQ(access["Solve"].size(), 1u);
  EXPECT_EQ(access["Solve"][0]["frames"], 2);
  EXPECT_EQ(access["Solve"][0]["status"], "OK");
  EXPECT_THAT(access["Solve"][0]["peer"].get<std::string>(), HasSubstr("127.0.0.1"));
  EXPECT_GE(access["Solve"][0]["ms"].get<double>(), 0.0);
  bool not_found = false;
  for (const auto& e : access["GetCharacter"]) not_found = not_found || e["status"] == "NOT_FOUND";
  EXPECT_TRUE(not_found) << "the refused describe has its access line";
  std::set<std::string> ids;
  for (const auto& e : access["ListCharacters"]) ids.insert(e["request_id"]);
  EXPECT_TRUE(ids.count("trace-abc-123"));
  EXPECT_TRUE(ids.count(made));
}

}  // namespace
}  // namespace springblend
