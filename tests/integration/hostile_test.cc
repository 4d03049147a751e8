// Hostile clients against a real 2-worker server (issue 19): requests built to hold the server (degenerate and
// oversized colliders, clients that stop reading or never send, uploads that declare more than they send,
// deletes racing rebuilds, malformed bytes, silent metrics connections). Each test checks the hostile request
// gets its bounded answer, and that a normal client gets the same correct frames during and after.
#include <fmt/format.h>
#include <gmock/gmock.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <future>
#include <sstream>
#include <thread>

#include "integration/server_process.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using testing::CylinderRig;
using testing::HttpGet;
using testing::ServerProcess;
using testing::SweepRequest;
using testing::TempDir;
using Clock = std::chrono::steady_clock;

std::unique_ptr<grpc::ClientContext> Context(int seconds = 20) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(seconds));
  return context;
}

grpc::Status SendSolve(v1::SolveService::Stub& stub, const v1::SolveRequest& request, int seconds = 20) {
  auto context = Context(seconds);
  auto reader = stub.Solve(context.get(), request);
  v1::SolvedFrame frame;
  while (reader->Read(&frame)) {
  }
  return reader->Finish();
}

// A closed 4-vertex OBJ (a tetrahedron's faces) with the given vertex lines.
std::string Tetrahedron(const std::string& vertices) {
  return vertices + "f 1 2 3\nf 1 4 2\nf 2 4 3\nf 3 4 1\n";
}

// A double cone around the z axis with `segments` segments: valid, closed, and each apex in `segments` faces.
std::string DoubleCone(int segments) {
  std::ostringstream obj;
  obj << "v 0 0 1\nv 0 0 -1\n";
  for (int i = 0; i < segments; ++i) {
    const double a = 2 * M_PI * i / segments;
    obj << "v " << std::cos(a) << " " << std::sin(a) << " 0\n";
  }
  for (int i = 0; i < segments; ++i) {
    const int p = 3 + i, q = 3 + (i + 1) % segments;
    obj << "f 1 " << p << " " << q << "\nf 2 " << q << " " << p << "\n";
  }
  return obj.str();
}

// One message on a streaming method through the generic stub: the final status and how many answers came.
std::pair<grpc::Status, int> GenericStream(const std::shared_ptr<grpc::Channel>& channel, const std::string& method,
                                           const std::string& bytes, const std::string& token = "") {
  grpc::GenericStub generic(channel);
  const grpc::Slice slice(bytes);
  const grpc::ByteBuffer message(&slice, 1);
  grpc::CompletionQueue cq;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  if (!token.empty()) context.AddMetadata("authorization", "Bearer " + token);
  auto call = generic.PrepareCall(&context, method, &cq);
  void* tag = nullptr;
  bool ok = false;
  const auto step = [&](void* expected) {
    while (cq.Next(&tag, &ok) && tag != expected) {
    }
    return ok;
  };
  call->StartCall(reinterpret_cast<void*>(1));
  step(reinterpret_cast<void*>(1));
  call->Write(message, reinterpret_cast<void*>(2));
  step(reinterpret_cast<void*>(2));
  call->WritesDone(reinterpret_cast<void*>(3));
  step(reinterpret_cast<void*>(3));
  int answers = 0;
  grpc::ByteBuffer response;
  for (;;) {
    call->Read(&response, reinterpret_cast<void*>(4));
    if (!step(reinterpret_cast<void*>(4))) break;
    ++answers;
  }
  grpc::Status status;
  call->Finish(&status, reinterpret_cast<void*>(5));
  step(reinterpret_cast<void*>(5));
  cq.Shutdown();
  while (cq.Next(&tag, &ok)) {
  }
  return {status, answers};
}

v1::SolveRequest WithMeshCollider(v1::SolveRequest request, const std::string& obj) {
  request.add_colliders()->set_mesh_obj(obj);
  return request;
}

class HostileTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    cache_ = new TempDir();
    log_ = (cache_->path() / "server.log").string();
    server_ = new ServerProcess((cache_->path() / "cache").string(),
                                {"--workers", "2", "--queue", "8", "--max-frames", "4000", "--stall-seconds", "1.5",
                                 "--idle-seconds", "2", "--request-memory-mb", "64", "--max-collider-faces", "20000",
                                 "--metrics", "127.0.0.1:0"},
                                log_);
    ASSERT_FALSE(server_->address().empty()) << "the server did not start";
    cylinder_ = new CylinderRig;
    Client client({server_->address(), std::chrono::seconds(60)});
    character_ = new v1::Character(client.Upload(cylinder_->rest, cylinder_->targets, {}, "cylinder"));
    reference_ = new std::vector<std::string>;
    client.Solve(Normal(), [](const v1::SolvedFrame& f) { reference_->push_back(f.positions()); });
  }
  static void TearDownTestSuite() {
    delete server_;
    delete cache_;
    delete cylinder_;
    delete character_;
    delete reference_;
  }

  void SetUp() override {
    channel_ = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
    characters_ = v1::CharacterService::NewStub(channel_);
    solves_ = v1::SolveService::NewStub(channel_);
  }

  static v1::SolveRequest Normal() { return SweepRequest(character_->id(), 3, {0.6, 0.3}); }

  // A normal client, on its own connection: the same frames, bit for bit, as when the server was idle, and
  // metadata calls answered, each within 15 s (a generous bound: the whole suite runs beside it on two cores).
  static void ExpectServed(const std::string& when) {
    Client client({server_->address(), std::chrono::seconds(15)});
    std::vector<std::string> frames;
    try {
      client.Solve(Normal(), [&](const v1::SolvedFrame& f) { frames.push_back(f.positions()); });
      EXPECT_EQ(client.Get(character_->id()).id(), character_->id()) << when;
      EXPECT_FALSE(client.List().empty()) << when;
    } catch (const ClientError& e) {
      ADD_FAILURE() << when << ": a normal client was refused: " << e.what();
    }
    EXPECT_EQ(frames, *reference_) << when;
    EXPECT_TRUE(client.Healthy()) << when;
  }

  static std::string Metrics() { return HttpGet(server_->metrics_port(), "/metrics"); }
  static double Metric(const std::string& name) {
    const std::string text = Metrics();
    const auto at = text.find("\n" + name + " ");
    return at == std::string::npos ? -1.0 : std::stod(text.substr(at + name.size() + 2));
  }
  // Until at most `bytes` are held (and the metric is there).
  static void WaitForRequestMemoryAtMost(double bytes, std::chrono::seconds limit) {
    const auto until = Clock::now() + limit;
    const auto held = [] { return Metric("springblend_request_memory_bytes"); };
    while (!(held() >= 0.0 && held() <= bytes) && Clock::now() < until) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    const double now = held();
    EXPECT_GE(now, 0.0);
    EXPECT_LE(now, bytes);
  }
  static void WaitForRequestMemory(double bytes, std::chrono::seconds limit) {
    const auto until = Clock::now() + limit;
    while (Metric("springblend_request_memory_bytes") != bytes && Clock::now() < until) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    EXPECT_EQ(Metric("springblend_request_memory_bytes"), bytes);
  }

  // Polls the pool's gauges until no worker is busy and nothing is queued, twice in a row 100 ms apart.
  static void WaitForIdlePool(std::chrono::seconds limit) {
    const auto until = Clock::now() + limit;
    int quiet = 0;
    while (quiet < 2 && Clock::now() < until) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      quiet = Metric("springblend_workers_busy") == 0 && Metric("springblend_queue_depth") == 0 ? quiet + 1 : 0;
    }
    EXPECT_EQ(quiet, 2) << "the pool stayed busy: " << Metric("springblend_workers_busy") << " workers, "
                        << Metric("springblend_queue_depth") << " queued";
  }

  static TempDir* cache_;
  static std::string log_;
  static ServerProcess* server_;
  static CylinderRig* cylinder_;
  static v1::Character* character_;
  static std::vector<std::string>* reference_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::CharacterService::Stub> characters_;
  std::unique_ptr<v1::SolveService::Stub> solves_;
};

TempDir* HostileTest::cache_ = nullptr;
std::string HostileTest::log_;
ServerProcess* HostileTest::server_ = nullptr;
CylinderRig* HostileTest::cylinder_ = nullptr;
v1::Character* HostileTest::character_ = nullptr;
std::vector<std::string>* HostileTest::reference_ = nullptr;

// 1. A degenerate mesh collider made CGAL's inside test loop for ever on a worker; two took the server down.
TEST_F(HostileTest, DegenerateMeshCollidersAreRefusedAtOnce) {
  // Vertices on one line through a rest vertex of the cylinder, and all on that vertex.
  const auto v = cylinder_->rest.vertices.row(0);
  std::ostringstream line, point;
  for (int i = 0; i < 4; ++i) line << "v " << v(0) + i << " " << v(1) << " " << v(2) << "\n";
  for (int i = 0; i < 4; ++i) point << "v " << v(0) << " " << v(1) << " " << v(2) << "\n";
  std::vector<std::future<grpc::Status>> hostile;
  for (const std::string& vertices : {line.str(), point.str(), line.str(), point.str()}) {
    hostile.push_back(std::async(std::launch::async, [&, obj = Tetrahedron(vertices)] {
      return SendSolve(*solves_, WithMeshCollider(Normal(), obj), 15);
    }));
  }
  for (auto& h : hostile) {
    const grpc::Status status = h.get();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr("colliders[0]"));
    EXPECT_THAT(status.error_message(), HasSubstr("degenerate"));
  }
  ExpectServed("after degenerate colliders");
}

// 3. Valence and corner counts made OpenMesh and CGAL cost quadratic CPU; caps refuse them in a linear pass.
TEST_F(HostileTest, ExpensiveMeshCollidersAreRefusedByTheirCaps) {
  const grpc::Status cone = SendSolve(*solves_, WithMeshCollider(Normal(), DoubleCone(8000)), 15);
  EXPECT_EQ(cone.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(cone.error_message(), HasSubstr("valence"));
  std::string polygon = DoubleCone(100) + "f";
  for (int i = 3; i < 103; ++i) polygon += fmt::format(" {}", i);
  for (int i = 0; i < 400; ++i) polygon += " 1";
  const grpc::Status corners = SendSolve(*solves_, WithMeshCollider(Normal(), polygon + "\n"), 15);
  EXPECT_EQ(corners.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(corners.error_message(), HasSubstr("corners"));
  // A modest valid cone is still a collider.
  const grpc::Status fine = SendSolve(*solves_, WithMeshCollider(Normal(), DoubleCone(64)));
  EXPECT_TRUE(fine.ok()) << fine.error_message();
  ExpectServed("after expensive colliders");
}

// 2. Clients that stop reading held a worker each in the write gate; two held a 2-worker server.
TEST_F(HostileTest, ClientsThatStopReadingHoldNoWorkerAndAreCutOff) {
  v1::SolveRequest big = SweepRequest(character_->id(), 3000, {1.0, 0.0});
  big.mutable_options()->set_linear(true);
  big.mutable_options()->set_with_normals(true);
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientReader<v1::SolvedFrame>>> readers;
  for (int i = 0; i < 3; ++i) {
    contexts.push_back(Context(60));
    readers.push_back(solves_->Solve(contexts.back().get(), big));  // and never read
  }
  // Interactive sessions that send frames and never read.
  std::vector<std::unique_ptr<grpc::ClientContext>> session_contexts;
  std::vector<std::unique_ptr<grpc::ClientReaderWriter<v1::InteractiveRequest, v1::SolvedFrame>>> sessions;
  for (int i = 0; i < 2; ++i) {
    session_contexts.push_back(Context(60));
    sessions.push_back(solves_->Interactive(session_contexts.back().get()));
    v1::InteractiveRequest start;
    start.mutable_start()->set_character_id(character_->id());
    start.mutable_start()->mutable_options()->set_linear(true);
    start.mutable_start()->mutable_options()->set_with_normals(true);
    sessions.back()->Write(start);
  }
  std::atomic<bool> stop{false};
  std::thread sender([&] {
    v1::InteractiveRequest frame;
    frame.mutable_frame()->add_weights(0.5);
    frame.mutable_frame()->add_weights(0.5);
    while (!stop) {
      for (auto& s : sessions) s->Write(frame);  // fails once the server has cut the session off
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
  });
  // The windows fill, and then none of them holds a worker or a place in the queue (under load that may take
  // longer than --stall-seconds, in which case they are cut off first: either way the pool comes back).
  WaitForIdlePool(std::chrono::seconds(20));
  ExpectServed("while 3 Solve streams and 2 sessions do not read");
  // Cut off after --stall-seconds (1.5 s): everything they held is released.
  WaitForRequestMemory(0, std::chrono::seconds(10));
  stop = true;
  sender.join();
  // The client reads the watchdog's reason, not gRPC's bare "Cancelled on the server side".
  for (auto& r : readers) {
    v1::SolvedFrame frame;
    while (r->Read(&frame)) {
    }
    const grpc::Status status = r->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED);
    EXPECT_THAT(status.error_message(), HasSubstr("stalled")) << status.error_message();
  }
  for (auto& s : sessions) {
    v1::SolvedFrame frame;
    while (s->Read(&frame)) {
    }
    const grpc::Status status = s->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED);
    EXPECT_THAT(status.error_message(), HasSubstr("stalled")) << status.error_message();
  }
  ExpectServed("after the stalled streams were cut off");
}

TEST_F(HostileTest, AnIdleInteractiveSessionIsClosed) {
  auto context = Context(30);
  auto session = solves_->Interactive(context.get());
  v1::InteractiveRequest start;
  start.mutable_start()->set_character_id(character_->id());
  ASSERT_TRUE(session->Write(start));
  const auto began = Clock::now();
  v1::SolvedFrame frame;
  while (session->Read(&frame)) {
  }
  const grpc::Status status = session->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED);
  EXPECT_THAT(status.error_message(), HasSubstr("idle for longer than --idle-seconds")) << status.error_message();
  EXPECT_LT(Clock::now() - began, std::chrono::seconds(20));  // --idle-seconds 2, not the call's deadline
  ExpectServed("after an idle session");
}

// Get, List and Delete ran on the solve pool: a full queue refused them, and they waited behind solves.
TEST_F(HostileTest, MetadataCallsDoNotWaitBehindSolves) {
  std::vector<std::future<grpc::Status>> load;
  for (int i = 0; i < 14; ++i) {
    load.push_back(std::async(std::launch::async, [&] {
      return SendSolve(*solves_, SweepRequest(character_->id(), 40, {1.0, 1.0}), 60);
    }));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  Client client({server_->address(), std::chrono::seconds(5)});
  for (int i = 0; i < 5; ++i) {
    EXPECT_NO_THROW(client.Get(character_->id()));
    EXPECT_NO_THROW(client.List());
    EXPECT_EQ(testing::StatusOf([&] { client.Delete(std::string(64, 'c')); }), grpc::StatusCode::NOT_FOUND);
  }
  int refused = 0;
  for (auto& f : load) {
    const grpc::Status s = f.get();
    if (!s.ok()) {
      EXPECT_EQ(s.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << s.error_message();
      ++refused;
    }
  }
  EXPECT_LT(refused, 14);
  ExpectServed("after a full queue");
}

// 4. An upload header alone allocated the whole declared character; now memory grows with the pieces, within one
// budget (--request-memory-mb) shared with open streams.
TEST_F(HostileTest, UploadsHoldOnlyWhatTheySentWithinTheBudget) {
  v1::UploadChunk header;
  header.mutable_header()->set_name("declares much, sends little");
  header.mutable_header()->set_vertex_count(2'000'000);
  header.mutable_header()->set_face_count(4'000'000);
  header.mutable_header()->add_target_names("a");
  header.mutable_header()->add_target_names("b");
  header.mutable_header()->add_target_names("c");
  const double rss_before = [&] {
    std::ifstream status("/proc/" + std::to_string(server_->pid()) + "/statm");
    double pages = 0, resident = 0;
    status >> pages >> resident;
    return resident * 4096.0 / (1 << 20);
  }();
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientWriter<v1::UploadChunk>>> writers;
  std::vector<v1::Character> responses(4);
  for (int i = 0; i < 4; ++i) {
    contexts.push_back(Context(30));
    writers.push_back(characters_->UploadCharacter(contexts.back().get(), &responses[static_cast<size_t>(i)]));
    ASSERT_TRUE(writers.back()->Write(header));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  const double rss_after = [&] {
    std::ifstream status("/proc/" + std::to_string(server_->pid()) + "/statm");
    double pages = 0, resident = 0;
    status >> pages >> resident;
    return resident * 4096.0 / (1 << 20);
  }();
  EXPECT_LT(rss_after - rss_before, 100.0) << "4 headers of 2M vertices (about 190 MB each, declared)";
  const double held_by_headers = Metric("springblend_request_memory_bytes");
  // One upload that sends pieces past the budget (64 MiB, counting twice what arrived) is refused.
  {
    auto context = Context(30);
    v1::Character response;
    auto writer = characters_->UploadCharacter(context.get(), &response);
    writer->Write(header);
    v1::UploadChunk piece;
    piece.mutable_piece()->set_kind(v1::MeshPiece::POSITIONS);
    const std::string bytes(24 * 40'000, '\0');
    for (int i = 0; i < 50; ++i) {  // 2M vertices in all; the budget refuses after about 33
      piece.mutable_piece()->set_offset(static_cast<std::uint32_t>(40'000 * i));
      piece.mutable_piece()->set_data(bytes);
      if (!writer->Write(piece)) break;
    }
    writer->WritesDone();
    const grpc::Status status = writer->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr("--request-memory-mb"));
  }
  // The refused upload's memory returns to the budget as its call ends, which may be just after its status
  // reached the client. What the stalled headers hold stays unless they were already cut off (--stall-seconds
  // 1.5 s: the refused upload's pieces can take longer than that on a loaded machine under the sanitizers).
  EXPECT_GT(held_by_headers, 0.0);
  WaitForRequestMemoryAtMost(held_by_headers, std::chrono::seconds(10));
  ExpectServed("with 4 stalled uploads open");
  // The stalled uploads are cut off after --stall-seconds and their memory returns to the budget.
  for (auto& w : writers) {
    const grpc::Status status = w->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED);
    EXPECT_THAT(status.error_message(), HasSubstr("stalled")) << status.error_message();
  }
  WaitForRequestMemory(0, std::chrono::seconds(10));
  ExpectServed("after the stalled uploads");
}

// 7. The smaller ones, each with the code and message a user can act on.
TEST_F(HostileTest, SmallerFindingsGetTheirStatusAndMessage) {
  // An id that is not a hex digest: INVALID_ARGUMENT, and the 100 KB id is not echoed back.
  {
    v1::GetCharacterRequest request;
    request.set_id(std::string(100'000, 'x'));
    v1::Character response;
    auto context = Context();
    const grpc::Status status = characters_->GetCharacter(context.get(), request, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_LT(status.error_message().size(), 300u);
    EXPECT_THAT(status.error_message(), HasSubstr("100000 bytes"));
  }
  // --max-frames: RESOURCE_EXHAUSTED, as the proto promises.
  {
    const grpc::Status status = SendSolve(*solves_, SweepRequest(character_->id(), 4001, {0.5, 0.5}));
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_THAT(status.error_message(), HasSubstr("--max-frames"));
  }
  // OBJ v lines that do not parse are refused naming the line.
  for (const std::string bad : {"v nan 0 0", "v 1,5 0 0", "v 1e400 0 0", "v 1 0", "v 1.0.0 0 0"}) {
    const std::string obj = "v 0 0 0\nv 1 0 0\n" + bad + "\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n";
    const grpc::Status status = SendSolve(*solves_, WithMeshCollider(Normal(), obj));
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << bad;
    EXPECT_THAT(status.error_message(), HasSubstr("line 3")) << bad;
  }
  // A weight of 1e308 no longer returns infinite coordinates as converged.
  {
    v1::SolveRequest request = SweepRequest(character_->id(), 1, {1e308, 0.0});
    request.mutable_frames(0)->set_weights(0, 1e308);
    request.mutable_options()->set_linear(true);
    const grpc::Status status = SendSolve(*solves_, request);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_THAT(status.error_message(), HasSubstr("frames[0]: weights[0]"));
  }
  // A plane whose normal overflows is refused, not silently ignored.
  {
    v1::SolveRequest request = Normal();
    v1::Plane* plane = request.add_colliders()->mutable_plane();
    plane->mutable_point()->set_y(-10);
    plane->mutable_normal()->set_x(1e200);
    plane->mutable_normal()->set_y(1e200);
    const grpc::Status status = SendSolve(*solves_, request);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_THAT(status.error_message(), HasSubstr("overflows"));
  }
  // An Interactive frame's error names that frame, not frames[0].
  {
    auto context = Context();
    auto session = solves_->Interactive(context.get());
    v1::InteractiveRequest message;
    message.mutable_start()->set_character_id(character_->id());
    ASSERT_TRUE(session->Write(message));
    v1::SolvedFrame answer;
    for (int i = 0; i < 2; ++i) {
      message.mutable_frame()->clear_weights();
      message.mutable_frame()->add_weights(0.1 * i);
      message.mutable_frame()->add_weights(0.0);
      ASSERT_TRUE(session->Write(message));
      ASSERT_TRUE(session->Read(&answer));
      EXPECT_EQ(answer.index(), static_cast<std::uint32_t>(i));
    }
    message.mutable_frame()->add_weights(0.0);  // three weights for two targets
    session->Write(message);
    session->WritesDone();
    while (session->Read(&answer)) {
    }
    const grpc::Status status = session->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_THAT(status.error_message(), HasSubstr("frames[2]"));
  }
  // Target names are bounded, and names reach log lines escaped.
  {
    CylinderRig rig;
    rig.targets[0].name = std::string(5 << 20, 'n');
    Client client({server_->address(), std::chrono::seconds(30)});
    std::string refusal;
    try {
      client.Upload(rig.rest, rig.targets);
    } catch (const std::exception& e) {
      refusal = e.what();
    }
    EXPECT_THAT(refusal, HasSubstr("over the limit of 256"));
    const v1::Character forged = client.Upload(rig.rest, {rig.targets[1]}, {}, "evil\n[info] forged line\x1b[31m");
    std::ifstream log(log_);
    const std::string text((std::istreambuf_iterator<char>(log)), std::istreambuf_iterator<char>());
    EXPECT_THAT(text, Not(HasSubstr("\n[info] forged line")));
    EXPECT_THAT(text, HasSubstr("evil\\x0a[info] forged line\\x1b[31m"));
    client.Delete(forged.id());
  }
  ExpectServed("after the smaller findings");
}

// Malformed bytes where a message belongs: INVALID_ARGUMENT with a message, not UNIMPLEMENTED (or OK).
TEST_F(HostileTest, UnparseableRequestBytesAreInvalidArgument) {
  grpc::GenericStub generic(channel_);
  const std::string garbage = "\xff\xff\xff\xff\xff\xff\xff\xff\x0f";
  const grpc::Slice slice(garbage);
  const grpc::ByteBuffer bad(&slice, 1);
  for (const std::string method : {"/springblend.v1.CharacterService/GetCharacter",
                                   "/springblend.v1.CharacterService/ListCharacters",
                                   "/springblend.v1.CharacterService/DeleteCharacter"}) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    std::promise<grpc::Status> done;
    grpc::ByteBuffer response;
    generic.UnaryCall(&context, method, grpc::StubOptions(), &bad, &response,
                      [&](grpc::Status s) { done.set_value(s); });
    const grpc::Status status = done.get_future().get();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << method;
    EXPECT_THAT(status.error_message(), HasSubstr("could not be parsed")) << method;
  }
  for (const std::string method : {"/springblend.v1.SolveService/Solve", "/springblend.v1.SolveService/Interactive",
                                   "/springblend.v1.CharacterService/UploadCharacter"}) {
    const auto [status, answers] = GenericStream(channel_, method, garbage);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << method << ": " << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr("could not be parsed")) << method;
    EXPECT_EQ(answers, 0);
  }
  ExpectServed("after unparseable requests");
}

// Reflection answered without a token although only health is open when tokens are configured.
TEST(HostileTokenTest, ReflectionNeedsATokenWhenTokensAreConfigured) {
  TempDir cache;
  ServerProcess server(cache.path().string(), {"--workers", "1", "--token", "s3cret"});
  const auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  const std::string list_services("\x3a\x00", 2);  // ServerReflectionRequest{list_services: ""}
  const std::string method = "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo";
  const auto [refused, leaked] = GenericStream(channel, method, list_services);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::UNAUTHENTICATED) << refused.error_message();
  EXPECT_THAT(refused.error_message(), HasSubstr("needs a token"));
  EXPECT_EQ(leaked, 0);
  const auto [wrong, none] = GenericStream(channel, method, list_services, "not-the-token");
  EXPECT_EQ(wrong.error_code(), grpc::StatusCode::UNAUTHENTICATED) << wrong.error_message();
  EXPECT_EQ(none, 0);
  const auto [served, answers] = GenericStream(channel, method, list_services, "s3cret");
  EXPECT_TRUE(served.ok()) << served.error_message();
  EXPECT_EQ(answers, 1);
  Client anonymous({server.address(), std::chrono::seconds(10)});
  EXPECT_TRUE(anonymous.Healthy()) << "health needs no token";
}

// The metrics responder served one connection at a time: 10 silent ones delayed a scrape by 20 s.
TEST_F(HostileTest, SilentMetricsConnectionsDoNotDelayAScrape) {
  std::vector<int> silent;
  for (int i = 0; i < 10; ++i) {
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(static_cast<std::uint16_t>(server_->metrics_port()));
    inet_pton(AF_INET, "127.0.0.1", &address.sin_addr);
    ASSERT_EQ(connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)), 0);
    silent.push_back(fd);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  const auto began = Clock::now();
  EXPECT_THAT(Metrics(), HasSubstr("springblend_frames_solved_total"));
  EXPECT_LT(Clock::now() - began, std::chrono::seconds(1));
  for (int fd : silent) close(fd);
}

// Every kind at once: a normal client keeps getting the same frames, Get and List within 5 s each, while
// degenerate and expensive colliders, readers that stop, uploads that stall, idle sessions and silent metrics
// connections all run against the 2-worker server.
TEST_F(HostileTest, ANormalClientIsServedWhileEveryKindRunsAtOnce) {
  std::atomic<bool> stop{false};
  std::vector<std::thread> hostile;
  const auto v = cylinder_->rest.vertices.row(0);
  std::ostringstream line;
  for (int i = 0; i < 4; ++i) line << "v " << v(0) + i << " " << v(1) << " " << v(2) << "\n";
  hostile.emplace_back([&, obj = Tetrahedron(line.str())] {
    while (!stop) SendSolve(*solves_, WithMeshCollider(Normal(), obj), 15);
  });
  hostile.emplace_back([&] {
    const std::string cone = DoubleCone(8000);
    while (!stop) SendSolve(*solves_, WithMeshCollider(Normal(), cone), 15);
  });
  hostile.emplace_back([&] {  // readers that stop reading, one after another
    v1::SolveRequest big = SweepRequest(character_->id(), 3000, {1.0, 0.0});
    big.mutable_options()->set_linear(true);
    while (!stop) {
      auto context = Context(30);
      auto reader = solves_->Solve(context.get(), big);
      for (int i = 0; i < 20 && !stop; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      context->TryCancel();
      reader->Finish();
    }
  });
  hostile.emplace_back([&] {  // uploads that send a header and stall
    v1::UploadChunk header;
    header.mutable_header()->set_vertex_count(2'000'000);
    header.mutable_header()->set_face_count(4'000'000);
    header.mutable_header()->add_target_names("a");
    while (!stop) {
      auto context = Context(30);
      v1::Character response;
      auto writer = characters_->UploadCharacter(context.get(), &response);
      writer->Write(header);
      for (int i = 0; i < 20 && !stop; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      context->TryCancel();
      writer->Finish();
    }
  });
  hostile.emplace_back([&] {  // idle sessions
    while (!stop) {
      auto context = Context(30);
      auto session = solves_->Interactive(context.get());
      v1::InteractiveRequest start;
      start.mutable_start()->set_character_id(character_->id());
      session->Write(start);
      for (int i = 0; i < 10 && !stop; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      context->TryCancel();
      session->Finish();
    }
  });
  std::vector<int> silent;
  for (int i = 0; i < 10; ++i) {
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(static_cast<std::uint16_t>(server_->metrics_port()));
    inet_pton(AF_INET, "127.0.0.1", &address.sin_addr);
    connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address));
    silent.push_back(fd);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));  // the readers' windows fill
  const auto began = Clock::now();
  for (int round = 0; round < 5 || Clock::now() - began < std::chrono::seconds(4); ++round) {
    ExpectServed("round " + std::to_string(round) + " with every kind of hostile client running");
    EXPECT_THAT(Metrics(), HasSubstr("springblend_frames_solved_total"));
  }
  stop = true;
  for (auto& t : hostile) t.join();
  for (int fd : silent) close(fd);
  ExpectServed("after every kind of hostile client");
}

// 5. The store: a delete wins over a rebuild in flight, concurrent builds of one id share one build, and a corrupt
// cache file is logged, removed and never listed.
TEST(HostileStoreTest, DeleteWinsOverARebuildAndBuildsAreShared) {
  TempDir cache;
  const std::string log = (cache.path() / "server.log").string();
  CylinderRig cylinder;
  std::string id, other;
  {
    ServerProcess server(cache.path().string(), {"--workers", "2"});
    Client client({server.address(), std::chrono::seconds(60)});
    id = client.Upload(cylinder.rest, cylinder.targets).id();
    other = client.Upload(cylinder.rest, {cylinder.targets[0]}).id();
  }
  // A corrupt file under a valid id.
  const std::string corrupt_id(64, 'a');
  {
    std::ofstream bad(cache.path() / (corrupt_id + ".sbchar"), std::ios::binary);
    bad << "SBCHAR01" << std::string(32, 'x') << std::string(100, 'y');
  }
  ServerProcess server(cache.path().string(), {"--workers", "2", "--metrics", "127.0.0.1:0"}, log);
  Client client({server.address(), std::chrono::seconds(60)});
  // Four concurrent first Gets of `other`: one rebuild.
  std::vector<std::future<std::string>> gets;
  for (int i = 0; i < 4; ++i) {
    gets.push_back(std::async(std::launch::async, [&] {
      Client c({server.address(), std::chrono::seconds(60)});
      return c.Get(other).id();
    }));
  }
  for (auto& g : gets) EXPECT_EQ(g.get(), other);
  EXPECT_THAT(HttpGet(server.metrics_port(), "/metrics"), HasSubstr("springblend_cache_rebuilds_from_disk_total 1\n"));
  // A Get that rebuilds `id` from its file, and a Delete while it does: the delete wins.
  auto get = std::async(std::launch::async, [&] {
    Client c({server.address(), std::chrono::seconds(60)});
    return testing::StatusOf([&] { c.Get(id); });
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  EXPECT_NO_THROW(client.Delete(id));
  get.get();
  EXPECT_EQ(testing::StatusOf([&] { client.Get(id); }), grpc::StatusCode::NOT_FOUND);
  EXPECT_FALSE(std::filesystem::exists(cache.path() / (id + ".sbchar")));
  // The corrupt file: not listed, removed, logged.
  std::vector<std::string> listed;
  for (const auto& c : client.List()) listed.push_back(c.id());
  EXPECT_THAT(listed, Not(::testing::Contains(corrupt_id)));
  EXPECT_THAT(listed, Not(::testing::Contains(id)));
  EXPECT_THAT(listed, ::testing::Contains(other));
  EXPECT_FALSE(std::filesystem::exists(cache.path() / (corrupt_id + ".sbchar")));
  std::ifstream in(log);
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_THAT(text, HasSubstr("is corrupt"));
}

}  // namespace
}  // namespace springblend
