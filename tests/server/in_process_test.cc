// The server composed by Server::Create and driven in-process (Server::InProcessChannel, no socket) through the
// C++ client library, on the bundled cylinder: uploads, streamed frames, error codes, mesh colliders as arrays
// and as OBJ text, colliders converted once per stream, a slow reader holding frames but no worker, cold
// characters built once for concurrent first requests, and draining on shutdown.
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <future>
#include <limits>
#include <set>
#include <sstream>
#include <thread>

#include "grpc/health/v1/health.grpc.pb.h"
#include "server.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend::server {
namespace {

using ::testing::HasSubstr;
using Clock = std::chrono::steady_clock;

struct Cylinder {
  TriangleMesh rest = LoadMesh(testing::DataPath("cylinder/cylinder.obj"));
  std::vector<TriangleMesh> targets = {LoadMesh(testing::DataPath("cylinder/poses-2_cylinder-1.obj")),
                                       LoadMesh(testing::DataPath("cylinder/poses-2_cylinder-3.obj"))};
};

// A closed, outward-oriented box as a triangle mesh; corners exact in float32, so OBJ text (read as float32)
// and float64 arrays describe the same collider.
TriangleMesh Box(const Eigen::Vector3d& center, double half) {
  TriangleMesh box;
  box.vertices.resize(8, 3);
  for (int i = 0; i < 8; ++i) {
    for (int a = 0; a < 3; ++a) box.vertices(i, a) = center[a] + ((i >> (2 - a)) & 1 ? half : -half);
  }
  std::vector<Eigen::Vector3i> triangles;
  for (int a = 0; a < 3; ++a) {
    const int b = (a + 1) % 3, c = (a + 2) % 3;
    for (int side = 0; side < 2; ++side) {
      int quad[4];
      const int corners[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      for (int k = 0; k < 4; ++k) {
        quad[k] = (side << (2 - a)) | (corners[k][0] << (2 - b)) | (corners[k][1] << (2 - c));
      }
      for (const auto& t : {Eigen::Vector3i(quad[0], quad[1], quad[2]), Eigen::Vector3i(quad[0], quad[2], quad[3])}) {
        const Eigen::Vector3d p0 = box.vertices.row(t[0]), p1 = box.vertices.row(t[1]), p2 = box.vertices.row(t[2]);
        const bool outward = (p1 - p0).cross(p2 - p0).dot((p0 + p1 + p2) / 3.0 - center) > 0.0;
        triangles.push_back(outward ? t : Eigen::Vector3i(t[0], t[2], t[1]));
      }
    }
  }
  box.faces.resize(static_cast<Eigen::Index>(triangles.size()), 3);
  for (size_t f = 0; f < triangles.size(); ++f) box.faces.row(static_cast<Eigen::Index>(f)) = triangles[f].transpose();
  return box;
}

std::string ObjText(const TriangleMesh& mesh) {
  std::ostringstream obj;
  obj.precision(17);
  for (Eigen::Index v = 0; v < mesh.vertices.rows(); ++v) {
    obj << "v " << mesh.vertices(v, 0) << " " << mesh.vertices(v, 1) << " " << mesh.vertices(v, 2) << "\n";
  }
  for (Eigen::Index f = 0; f < mesh.faces.rows(); ++f) {
    obj << "f " << mesh.faces(f, 0) + 1 << " " << mesh.faces(f, 1) + 1 << " " << mesh.faces(f, 2) + 1 << "\n";
  }
  return obj.str();
}

v1::SolveRequest Sweep(const std::string& id, int frames, const std::vector<double>& end = {0.8, 0.4}) {
  v1::SolveRequest request;
  request.set_character_id(id);
  for (const Frame& frame : SweepFrames(end, frames)) {
    v1::FrameRequest* f = request.add_frames();
    for (double w : frame.weights) f->add_weights(w);
  }
  return request;
}

// The value of an unlabelled counter or gauge in the server's metrics text.
double Metric(const Server& server, const std::string& name) {
  const std::string text = server.MetricsText();
  const size_t at = text.find("\n" + name + " ");
  if (at == std::string::npos) {
    ADD_FAILURE() << name << " is not in the metrics";
    return -1;
  }
  return std::stod(text.substr(at + name.size() + 2));
}

grpc::StatusCode CodeOf(const std::function<void()>& call, std::string* message = nullptr) {
  try {
    call();
  } catch (const ClientError& e) {
    if (message) *message = e.what();
    return static_cast<grpc::StatusCode>(e.code());
  }
  return grpc::StatusCode::OK;
}

class InProcessServerTest : public ::testing::Test {
 protected:
  static ServerOptions Options(const std::string& cache_dir) {
    ServerOptions options;
    options.listen = {};  // in-process only
    options.cache_dir = cache_dir;
    options.workers = 2;
    options.limits.max_frames = 64;
    options.limits.SetMaxColliderFaces(1000);
    options.replica_name = "in-process";
    options.drain = std::chrono::seconds(20);
    return options;
  }
  void SetUp() override {
    server_ = Server::Create(Options(cache_.path().string()));
    client_ = std::make_unique<Client>(server_->InProcessChannel());
  }
  // The cylinder without target paths: a build of a fraction of a second, enough for the server's behaviour.
  std::string UploadCylinder(Client& client, size_t targets = 2) {
    v1::BuildOptions options;
    options.set_no_target_paths(true);
    return client.Upload(cylinder_.rest, {cylinder_.targets.begin(), cylinder_.targets.begin() + targets}, options)
        .id();
  }

  testing::TempDir cache_;
  Cylinder cylinder_;
  std::unique_ptr<Server> server_;
  std::unique_ptr<Client> client_;
};

TEST_F(InProcessServerTest, UploadsTheCylinderAndStreamsEveryFrameInOrder) {
  const v1::Character character = client_->Upload(cylinder_.rest, cylinder_.targets, {}, "cylinder");
  EXPECT_FALSE(character.cache_hit());
  EXPECT_EQ(character.summary().surface_vertices(), static_cast<unsigned>(cylinder_.rest.vertices.rows()));
  EXPECT_TRUE(client_->Upload(cylinder_.rest, cylinder_.targets, {}, "cylinder").cache_hit());
  EXPECT_TRUE(client_->Healthy());

  std::vector<Points> frames;
  const int received = client_->Solve(Sweep(character.id(), 6), [&](const v1::SolvedFrame& frame) {
    EXPECT_EQ(frame.index(), frames.size());
    EXPECT_TRUE(frame.summary().converged()) << frame.summary().message();
    EXPECT_EQ(frame.summary().served_by(), "in-process");
    frames.push_back(Client::Decode(frame.positions()));
  });
  EXPECT_EQ(received, 6);
  ASSERT_EQ(frames.size(), 6u);
  // Frame 0 is the rest shape, the last one moved towards the targets.
  EXPECT_LT(testing::MaxDistance(frames[0], cylinder_.rest.vertices), 1e-5);
  EXPECT_GT(testing::MaxDistance(frames[5], cylinder_.rest.vertices), 0.1);
  EXPECT_EQ(Metric(*server_, "springblend_frames_solved_total"), 6);
  EXPECT_EQ(server_->stats().store.builds, 1);
  EXPECT_THAT(server_->MetricsText(), HasSubstr("springblend_requests_total{method=\"Solve\",code=\"OK\"} 1\n"));
}

// Every refusal through the one error map: the code and a message naming the field.
TEST_F(InProcessServerTest, RefusalsCarryTheirCodeAndNameTheField) {
  const std::string id = UploadCylinder(*client_);
  const auto solve = [&](const v1::SolveRequest& request) {
    return [&, request] { client_->Solve(request, [](const v1::SolvedFrame&) {}); };
  };
  std::string message;
  EXPECT_EQ(CodeOf(solve(Sweep(std::string(64, 'a'), 2)), &message), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(message, HasSubstr("upload it first"));
  // A limit is RESOURCE_EXHAUSTED, like the upload limits.
  EXPECT_EQ(CodeOf(solve(Sweep(id, 65)), &message), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(message, HasSubstr("65 frames is over the limit of 64 (--max-frames)"));
  v1::SolveRequest many = Sweep(id, 2);
  for (int i = 0; i < 65; ++i) *many.add_colliders() = MeshCollider(Box({0, 3, 0}, 0.25).vertices, Box({0, 3, 0}, 0.25).faces);
  EXPECT_EQ(CodeOf(solve(many), &message), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(message, HasSubstr("65 colliders is over the limit of 64"));
  v1::SolveRequest nan = Sweep(id, 2);
  nan.mutable_frames(1)->set_weights(0, std::numeric_limits<double>::quiet_NaN());
  EXPECT_EQ(CodeOf(solve(nan), &message), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(message, HasSubstr("frames[1]: weights[0]"));
  EXPECT_EQ(CodeOf([&] { client_->Get("../etc/passwd"); }, &message), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(message, HasSubstr("is not a character id"));
  EXPECT_THAT(server_->MetricsText(),
              HasSubstr("springblend_requests_total{method=\"Solve\",code=\"RESOURCE_EXHAUSTED\"} 2\n"));
}

// A mesh collider as arrays gives the frames of the same mesh as OBJ text, converted once per request; bad
// arrays are refused naming the array and the index.
TEST_F(InProcessServerTest, AMeshColliderAsArraysGivesTheFramesOfItsObjText) {
  const std::string id = UploadCylinder(*client_);
  const TriangleMesh box = Box({-1.75, 0.75, 0.75}, 0.25);
  const auto solve = [&](const v1::Collider& collider) {
    v1::SolveRequest request = Sweep(id, 4);
    *request.add_colliders() = collider;
    std::vector<v1::SolvedFrame> frames;
    client_->Solve(request, [&](const v1::SolvedFrame& f) { frames.push_back(f); });
    return frames;
  };
  v1::Collider text;
  text.set_mesh_obj(ObjText(box));
  const double converted = Metric(*server_, "springblend_colliders_converted_total");
  const std::vector<v1::SolvedFrame> as_text = solve(text);
  const std::vector<v1::SolvedFrame> as_arrays = solve(MeshCollider(box.vertices, box.faces));
  EXPECT_EQ(Metric(*server_, "springblend_colliders_converted_total"), converted + 2) << "once per request";
  ASSERT_EQ(as_text.size(), 4u);
  ASSERT_EQ(as_arrays.size(), 4u);
  unsigned contacts = 0;
  for (size_t i = 0; i < 4; ++i) {
    EXPECT_EQ(as_arrays[i].positions(), as_text[i].positions()) << "frame " << i;
    EXPECT_EQ(as_arrays[i].summary().contacts(), as_text[i].summary().contacts());
    contacts += as_arrays[i].summary().contacts();
  }
  EXPECT_GT(contacts, 0u) << "the box is in the cylinder's way";

  const auto refusal = [&](const std::function<void(v1::MeshArrays&)>& change) {
    v1::Collider collider = MeshCollider(box.vertices, box.faces);
    change(*collider.mutable_mesh());
    std::string message;
    const grpc::StatusCode code = CodeOf([&] { solve(collider); }, &message);
    return std::make_pair(code, message);
  };
  const auto invalid = [](const std::pair<grpc::StatusCode, std::string>& r) {
    EXPECT_EQ(r.first, grpc::StatusCode::INVALID_ARGUMENT) << r.second;
    return r.second;
  };
  auto set_int = [](std::string& bytes, size_t index, int value) { std::memcpy(bytes.data() + 4 * index, &value, 4); };
  auto set_double = [](std::string& bytes, size_t index, double value) {
    std::memcpy(bytes.data() + 8 * index, &value, 8);
  };
  EXPECT_THAT(invalid(refusal([&](v1::MeshArrays& m) { set_int(*m.mutable_triangles(), 3 * 5 + 1, 99); })),
              HasSubstr("colliders[0]: mesh.triangles[5] refers to vertex 99, but mesh.positions has 8 vertices"));
  EXPECT_THAT(invalid(refusal([&](v1::MeshArrays& m) { set_int(*m.mutable_triangles(), 3 * 2, -1); })),
              HasSubstr("mesh.triangles[2] refers to vertex -1"));
  EXPECT_THAT(invalid(refusal([&](v1::MeshArrays& m) {
                set_double(*m.mutable_positions(), 3 * 3 + 1, std::numeric_limits<double>::infinity());
              })),
              HasSubstr("colliders[0]: mesh.positions: vertex 3 has a non-finite y coordinate"));
  EXPECT_THAT(invalid(refusal([&](v1::MeshArrays& m) { m.mutable_positions()->pop_back(); })),
              HasSubstr("mesh.positions has 191 bytes, not a multiple of 24"));
  EXPECT_THAT(invalid(refusal([&](v1::MeshArrays& m) { m.mutable_triangles()->resize(12 * 11); })),
              HasSubstr("closed"));
  const auto over = refusal([&](v1::MeshArrays& m) { m.mutable_positions()->resize(24 * 1001); });
  EXPECT_EQ(over.first, grpc::StatusCode::RESOURCE_EXHAUSTED) << over.second;
  EXPECT_THAT(over.second, HasSubstr("colliders[0].mesh.positions has 1001 vertices, over the limit of 1000 "
                                     "(--max-collider-faces)"));
}

// An Interactive session converts its colliders at the start, not per frame; every frame sent (after the
// previous answer) is answered.
TEST_F(InProcessServerTest, InteractiveConvertsItsCollidersOnceAndAnswersEveryFrame) {
  const std::string id = UploadCylinder(*client_);
  const TriangleMesh box = Box({-1.75, 0.75, 0.75}, 0.25);
  v1::InteractiveStart start;
  start.set_character_id(id);
  *start.add_colliders() = MeshCollider(box.vertices, box.faces);
  start.add_colliders()->mutable_sphere()->set_radius(0.1);
  const double converted = Metric(*server_, "springblend_colliders_converted_total");
  auto session = client_->StartInteractive(start);
  for (int i = 0; i < 5; ++i) {
    v1::FrameRequest frame;
    frame.add_weights(0.15 * i);
    frame.add_weights(0.05 * i);
    ASSERT_TRUE(session->Send(frame));
    v1::SolvedFrame answer;
    ASSERT_TRUE(session->Next(&answer));
    EXPECT_EQ(answer.index(), static_cast<unsigned>(i));
  }
  session->Close();
  v1::SolvedFrame rest;
  EXPECT_FALSE(session->Next(&rest));
  EXPECT_NO_THROW(session->Finish());
  EXPECT_EQ(Metric(*server_, "springblend_colliders_converted_total"), converted + 2) << "two colliders, once";
  EXPECT_EQ(Metric(*server_, "springblend_frames_solved_total"), 5);
}

// With previews, a frame taken up is answered at once by the rig's prediction (here, without target paths,
// the linear blend), marked not converged, then by its solve: the one-frame Solve of the same weights.
TEST_F(InProcessServerTest, InteractivePreviewsComeFirstThenTheSolve) {
  const std::string id = UploadCylinder(*client_);
  RigOptions local;
  local.target_paths = false;
  const auto rig = Rig::Build(cylinder_.rest, cylinder_.targets, local);
  const double diagonal = rig->summary().bounding_box_diagonal;
  v1::InteractiveStart start;
  start.set_character_id(id);
  start.set_previews(true);
  auto session = client_->StartInteractive(start);
  v1::FrameRequest frame;
  frame.add_weights(0.7);
  frame.add_weights(0.3);
  ASSERT_TRUE(session->Send(frame));
  v1::SolvedFrame preview, solved;
  ASSERT_TRUE(session->Next(&preview));
  ASSERT_TRUE(session->Next(&solved));
  session->Close();
  v1::SolvedFrame more;
  EXPECT_FALSE(session->Next(&more));
  EXPECT_NO_THROW(session->Finish());
  EXPECT_EQ(preview.index(), 0u);
  EXPECT_FALSE(preview.summary().converged());
  EXPECT_EQ(preview.summary().termination(), "preview");
  EXPECT_LE(testing::MaxDistance(Client::Decode(preview.positions()), LinearBlend(*rig, {0.7, 0.3})), 1e-6 * diagonal);
  EXPECT_EQ(solved.index(), 0u);
  EXPECT_TRUE(solved.summary().converged());
  v1::SolveRequest request;
  request.set_character_id(id);
  *request.add_frames() = frame;
  std::string alone;
  client_->Solve(request, [&](const v1::SolvedFrame& f) { alone = f.positions(); });
  EXPECT_EQ(solved.positions(), alone) << "the settled answer is the one-frame Solve";
  EXPECT_GT(testing::MaxDistance(Client::Decode(preview.positions()), Client::Decode(alone)), 1e-4 * diagonal)
      << "the preview is not already the answer (else this test shows nothing)";
}

// A burst of frames with previews: every answer is a preview or a solve of a frame sent, by increasing frame,
// a preview never after its frame's solve, and the last frame's solve ends the stream.
TEST_F(InProcessServerTest, InteractivePreviewsOfABurstEndWithTheLastFrameSolved) {
  const std::string id = UploadCylinder(*client_);
  v1::InteractiveStart start;
  start.set_character_id(id);
  start.set_previews(true);
  auto session = client_->StartInteractive(start);
  constexpr int kFrames = 20;
  for (int i = 0; i < kFrames; ++i) {
    v1::FrameRequest frame;
    frame.add_weights(0.05 * i);
    frame.add_weights(0.02 * i);
    ASSERT_TRUE(session->Send(frame));
  }
  session->Close();
  std::vector<v1::SolvedFrame> answers;
  for (v1::SolvedFrame answer; session->Next(&answer);) answers.push_back(answer);
  EXPECT_NO_THROW(session->Finish());
  ASSERT_FALSE(answers.empty());
  std::set<unsigned> previewed, solved;
  unsigned newest = 0;
  for (const v1::SolvedFrame& answer : answers) {
    ASSERT_LT(answer.index(), static_cast<unsigned>(kFrames));
    EXPECT_GE(answer.index(), newest) << "answers never go back to an older frame";
    newest = answer.index();
    if (answer.summary().termination() == "preview") {
      EXPECT_FALSE(answer.summary().converged());
      EXPECT_TRUE(previewed.insert(answer.index()).second) << "one preview per frame";
      EXPECT_FALSE(solved.count(answer.index())) << "no preview after its frame's solve";
    } else {
      EXPECT_TRUE(answer.summary().converged()) << answer.summary().message();
      EXPECT_TRUE(solved.insert(answer.index()).second) << "one solve per frame";
    }
  }
  EXPECT_EQ(answers.back().index(), static_cast<unsigned>(kFrames - 1));
  EXPECT_TRUE(answers.back().summary().converged()) << "the last frame is solved";
}

// A reader that stops reading holds at most the frames in flight (one being written, up to one per worker
// solved and waiting), and no worker: every worker returns to the pool, and other requests are served meanwhile.
TEST_F(InProcessServerTest, ASlowReaderHoldsFramesButNoWorker) {
  const std::string id = UploadCylinder(*client_);
  auto stub = v1::SolveService::NewStub(server_->InProcessChannel());
  grpc::ClientContext context;
  auto reader = stub->Solve(&context, Sweep(id, 40));
  v1::SolvedFrame frame;
  ASSERT_TRUE(reader->Read(&frame));
  // The server settles: nothing running, nothing queued, while the stream stays open.
  const auto until = Clock::now() + std::chrono::seconds(20);
  double solved = 0;
  for (double last = -1; Clock::now() < until; last = solved) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    solved = Metric(*server_, "springblend_frames_solved_total");
    const ServerStats stats = server_->stats();
    if (solved == last && stats.workers_busy == 0 && stats.queue_depth == 0) break;
  }
  const ServerStats stats = server_->stats();
  EXPECT_EQ(stats.workers_busy, 0);
  EXPECT_EQ(stats.queue_depth, 0);
  EXPECT_LE(solved, 1 + 1 + stats.workers) << "read, being written, one per worker";
  EXPECT_LT(solved, 40);
  EXPECT_GT(stats.request_memory_bytes, 0) << "the open stream is counted";
  // Meanwhile the workers serve another client.
  EXPECT_EQ(client_->Solve(Sweep(id, 3), [](const v1::SolvedFrame&) {}), 3);
  int read = 1;
  while (reader->Read(&frame)) {
    EXPECT_EQ(frame.index(), static_cast<unsigned>(read));
    ++read;
  }
  EXPECT_TRUE(reader->Finish().ok());
  EXPECT_EQ(read, 40);
}

// Concurrent first requests for a character that is only in the cache directory build it once; concurrent
// uploads of a new character build it once too.
TEST_F(InProcessServerTest, ConcurrentFirstRequestsForAColdCharacterBuildItOnce) {
  const std::string id = UploadCylinder(*client_);
  client_.reset();
  server_.reset();  // the character is now only in the cache directory
  server_ = Server::Create(Options(cache_.path().string()));
  const auto concurrently = [&](int count, const std::function<void(Client&)>& call) {
    std::vector<std::future<void>> calls;
    for (int i = 0; i < count; ++i) {
      calls.push_back(std::async(std::launch::async, [&] {
        Client client(server_->InProcessChannel());
        call(client);
      }));
    }
    for (auto& c : calls) c.get();
  };
  concurrently(4, [&](Client& client) { EXPECT_EQ(client.Solve(Sweep(id, 2), [](const v1::SolvedFrame&) {}), 2); });
  EXPECT_EQ(server_->stats().store.builds, 1);
  EXPECT_EQ(server_->stats().store.rebuilds_from_disk, 1);
  EXPECT_EQ(Metric(*server_, "springblend_cache_builds_total"), 1);

  std::atomic<int> new_uploads{0};
  concurrently(3, [&](Client& client) {
    if (!client.Upload(cylinder_.rest, {cylinder_.targets[0]}).cache_hit()) ++new_uploads;
  });
  EXPECT_EQ(server_->stats().store.builds, 2);
  EXPECT_EQ(new_uploads, 1);
}

// A restarted server (a new Server on the same cache directory) loads the character's target paths from its
// cache file instead of solving them, and serves the very frames the first server did.
TEST_F(InProcessServerTest, ARestartedServerLoadsThePathsAndServesTheSameFrames) {
  const v1::Character first = client_->Upload(cylinder_.rest, cylinder_.targets, {}, "cylinder");
  const v1::RigSummary& built = first.summary();
  EXPECT_FALSE(built.paths_loaded());
  EXPECT_GT(built.path_samples(), 0u);
  EXPECT_GT(built.path_ms(), 0.0);
  EXPECT_GT(built.path_bytes(), 0u);
  EXPECT_GT(built.rig_bytes(), 0u);
  EXPECT_GE(built.path_max_error(), 0.0);
  // Per target: its name, samples and build time; the summary's totals are their sums.
  ASSERT_EQ(built.paths_size(), static_cast<int>(cylinder_.targets.size()));
  std::uint32_t samples = 0, uncertified = 0;
  for (int t = 0; t < built.paths_size(); ++t) {
    const v1::TargetPathSummary& p = built.paths(t);
    EXPECT_EQ(p.target(), first.target_names(t));
    EXPECT_GT(p.ms(), 0.0);
    EXPECT_LE(p.local_checks(), p.checks());
    EXPECT_LE(p.max_error(), built.path_max_error());
    EXPECT_LE(p.uncertified_ranges_size(), static_cast<int>(p.uncertified()));
    samples += p.samples();
    uncertified += p.uncertified();
  }
  EXPECT_EQ(samples, built.path_samples());
  EXPECT_EQ(uncertified, built.uncertified_path_intervals());
  // The samples were written to the cache file as soon as they were solved, and are read from there.
  EXPECT_GT(built.path_file_bytes(), 20 * built.path_bytes());
  std::vector<v1::SolvedFrame> before, after;
  client_->Solve(Sweep(first.id(), 5), [&](const v1::SolvedFrame& f) { before.push_back(f); });
  client_.reset();
  server_.reset();
  server_ = Server::Create(Options(cache_.path().string()));
  client_ = std::make_unique<Client>(server_->InProcessChannel());
  const v1::Character again = client_->Get(first.id());
  EXPECT_TRUE(again.summary().paths_loaded());
  EXPECT_EQ(again.summary().path_samples(), built.path_samples());
  EXPECT_EQ(again.summary().uncertified_path_intervals(), built.uncertified_path_intervals());
  EXPECT_EQ(again.summary().path_ms(), 0.0) << "nothing solved";
  ASSERT_EQ(again.summary().paths_size(), built.paths_size());
  for (int t = 0; t < built.paths_size(); ++t) {
    const v1::TargetPathSummary& loaded = again.summary().paths(t);
    EXPECT_EQ(loaded.target(), built.paths(t).target());
    EXPECT_EQ(loaded.samples(), built.paths(t).samples());
    EXPECT_EQ(loaded.ms(), 0.0);
    // Where frames may need a full solve is part of what the cache file keeps.
    ASSERT_EQ(loaded.uncertified_ranges_size(), built.paths(t).uncertified_ranges_size());
    for (int r = 0; r < loaded.uncertified_ranges_size(); ++r) {
      EXPECT_EQ(loaded.uncertified_ranges(r).low(), built.paths(t).uncertified_ranges(r).low());
      EXPECT_EQ(loaded.uncertified_ranges(r).high(), built.paths(t).uncertified_ranges(r).high());
    }
  }
  EXPECT_EQ(again.summary().path_file_bytes(), built.path_file_bytes());
  EXPECT_EQ(again.summary().path_bytes(), built.path_bytes());
  client_->Solve(Sweep(first.id(), 5), [&](const v1::SolvedFrame& f) { after.push_back(f); });
  ASSERT_EQ(before.size(), 5u);
  ASSERT_EQ(after.size(), 5u);
  for (size_t i = 0; i < 5; ++i) {
    EXPECT_EQ(after[i].positions(), before[i].positions()) << "frame " << i;
    const v1::FrameSummary& s = after[i].summary();
    EXPECT_THAT(s.finish(), ::testing::AnyOf("full", "local")) << "frame " << i;
    EXPECT_EQ(s.finish(), before[i].summary().finish());
    EXPECT_GT(s.free_vertices(), 0u);
    EXPECT_LE(s.solved_vertices(), s.free_vertices());
  }
  EXPECT_EQ(server_->stats().store.paths_loaded, 1);
  EXPECT_EQ(server_->stats().store.rebuilds_from_disk, 1);
}

std::vector<TriangleMesh> CubeTargets() {
  std::vector<TriangleMesh> targets;
  for (int i = 1; i <= 4; ++i) {
    targets.push_back(LoadMesh(testing::DataPath("cube/poses-1_cube-" + std::to_string(i) + ".obj")));
  }
  return targets;
}

// An upload whose deadline passes while its rig is built (the cube's takes about ten seconds) stops the build:
// the client is answered at its deadline, the server's worker is free soon after, and nothing is kept.
TEST_F(InProcessServerTest, AnUploadPastItsDeadlineStopsItsBuild) {
  ClientOptions options;
  options.timeout = std::chrono::milliseconds(1500);
  Client hasty(server_->InProcessChannel(), options);
  const auto start = Clock::now();
  EXPECT_EQ(CodeOf([&] { hasty.Upload(LoadMesh(testing::DataPath("cube/cube.obj")), CubeTargets()); }),
            grpc::StatusCode::DEADLINE_EXCEEDED);
  const auto until = Clock::now() + std::chrono::milliseconds(static_cast<int>(5000 * testing::kSlowdown));
  while (server_->stats().store.cancelled_builds == 0 && Clock::now() < until) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_EQ(server_->stats().store.cancelled_builds, 1);
  EXPECT_LT(Clock::now() - start, std::chrono::milliseconds(static_cast<int>(4000 * testing::kSlowdown)))
      << "stopped, not built to the end";
  EXPECT_EQ(server_->stats().store.characters, 0);
  EXPECT_TRUE(std::filesystem::is_empty(cache_.path()));
}

// A shutdown is not held up by a long build: once its drain is over, the build stops. Over a network port
// (in-process calls are cancelled at once by a shutdown).
TEST_F(InProcessServerTest, ShutdownStopsABuildOnceItsDrainIsOver) {
  ServerOptions options = Options(cache_.path().string());
  options.listen = {"127.0.0.1:0"};
  options.drain = std::chrono::milliseconds(300);
  server_ = Server::Create(options);
  auto upload = std::async(std::launch::async, [&] {
    Client client({server_->addresses()[0]});
    return CodeOf([&] { client.Upload(LoadMesh(testing::DataPath("cube/cube.obj")), CubeTargets()); });
  });
  const auto until = Clock::now() + std::chrono::seconds(5);
  while (server_->stats().store.builds == 0 && Clock::now() < until) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  const auto start = Clock::now();
  server_->Shutdown();
  EXPECT_LT(Clock::now() - start, std::chrono::milliseconds(static_cast<int>(2000 * testing::kSlowdown)));
  EXPECT_NE(upload.get(), grpc::StatusCode::OK);
  EXPECT_EQ(server_->stats().store.cancelled_builds, 1);
  EXPECT_TRUE(std::filesystem::is_empty(cache_.path()));
}

// Shutdown drains: health says NOT_SERVING at once, a stream in flight (64 frames, read after the shutdown
// began) finishes with every frame, new calls are refused, and Shutdown returns once the stream has ended. A
// network port and the health port serve too.
TEST_F(InProcessServerTest, ShutdownDrainsAStreamInFlight) {
  ServerOptions options = Options("");
  options.listen = {"127.0.0.1:0"};
  options.health_listen = "127.0.0.1:0";
  server_ = Server::Create(options);
  ASSERT_EQ(server_->addresses().size(), 1u);
  Client network({server_->addresses()[0]});
  EXPECT_TRUE(network.Healthy());
  const std::string id = UploadCylinder(network);
  auto health = grpc::health::v1::Health::NewStub(
      grpc::CreateChannel("127.0.0.1:" + std::to_string(server_->health_port()), grpc::InsecureChannelCredentials()));
  const auto serving = [&] {
    grpc::ClientContext context;
    grpc::health::v1::HealthCheckResponse response;
    health->Check(&context, {}, &response);
    return response.status();
  };
  EXPECT_EQ(serving(), grpc::health::v1::HealthCheckResponse::SERVING);

  // Over the network port: gRPC's in-process transport closes its streams when the server says goaway, so
  // in-process calls are cancelled by Shutdown rather than drained.
  auto stub = v1::SolveService::NewStub(
      grpc::CreateChannel(server_->addresses()[0], grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  auto reader = stub->Solve(&context, Sweep(id, 64));
  v1::SolvedFrame frame;
  ASSERT_TRUE(reader->Read(&frame));
  auto shutdown = std::async(std::launch::async, [&] { server_->Shutdown(); });
  const auto until = Clock::now() + std::chrono::seconds(10);
  while (serving() != grpc::health::v1::HealthCheckResponse::NOT_SERVING && Clock::now() < until) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_EQ(serving(), grpc::health::v1::HealthCheckResponse::NOT_SERVING);
  // Health says NOT_SERVING as Shutdown begins, a moment before the server stops taking calls (a wider moment on
  // a loaded machine under the sanitizers): new calls are refused within seconds, while the stream still drains.
  grpc::StatusCode refused = grpc::StatusCode::OK;
  while ((refused = CodeOf([&] { network.Get(id); })) == grpc::StatusCode::OK && Clock::now() < until) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_NE(refused, grpc::StatusCode::OK) << "new calls are refused while draining";
  int read = 1;
  while (reader->Read(&frame)) ++read;
  EXPECT_TRUE(reader->Finish().ok());
  EXPECT_EQ(read, 64);
  EXPECT_EQ(shutdown.wait_for(std::chrono::seconds(10)), std::future_status::ready);
}

// Without time to drain, Shutdown cancels a stream nobody reads instead of waiting for it.
TEST_F(InProcessServerTest, ShutdownWithoutDrainCancelsAStalledStream) {
  ServerOptions options = Options("");
  options.drain = std::chrono::milliseconds(0);
  server_ = Server::Create(options);
  Client client(server_->InProcessChannel());
  const std::string id = UploadCylinder(client);
  auto stub = v1::SolveService::NewStub(server_->InProcessChannel());
  grpc::ClientContext context;
  auto reader = stub->Solve(&context, Sweep(id, 20));
  v1::SolvedFrame frame;
  ASSERT_TRUE(reader->Read(&frame));
  const auto start = Clock::now();
  server_->Shutdown();
  EXPECT_LT(Clock::now() - start, std::chrono::seconds(10));
  while (reader->Read(&frame)) {
  }
  EXPECT_FALSE(reader->Finish().ok());
}

TEST(ServerOptionsTest, RefusesBadValuesNamingTheField) {
  ServerOptions options;
  options.listen = {"127.0.0.1:99999"};
  EXPECT_THAT(testing::CatchError([&] { Server::Create(options); }).what(), HasSubstr("--listen 127.0.0.1:99999"));
  options.listen = {};
  options.queue = 0;
  EXPECT_THAT(testing::CatchError([&] { options.Validate(); }).what(), HasSubstr("queue = 0"));
}

}  // namespace
}  // namespace springblend::server
