// Every malformed request we could think of, sent through raw gRPC stubs (the client library would catch some
// of them first): each must get the right status code and a message naming what is wrong, while a healthy
// client solving at the same time keeps getting the same correct frames and no cached character changes.
#include <fmt/format.h>
#include <gmock/gmock.h>
#include <google/protobuf/unknown_field_set.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <filesystem>
#include <limits>
#include <set>
#include <thread>

#include "integration/server_process.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend {
namespace {

using testing::CylinderRig;
using testing::ServerProcess;
using testing::SweepRequest;
using testing::TempDir;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

std::unique_ptr<grpc::ClientContext> Context() {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(60));
  return context;
}

// An upload as the wire sees it: the header, then pieces. Built valid from a mesh, then broken per case.
struct Upload {
  v1::UploadHeader header;
  std::vector<int> faces;               // 3 per face
  std::vector<std::vector<double>> shapes;  // rest, then targets; 3 per vertex
  std::vector<v1::UploadChunk> extra;   // appended after the pieces

  static Upload Of(const TriangleMesh& rest, const std::vector<TriangleMesh>& targets) {
    Upload u;
    u.header.set_name("bad input");
    u.header.set_vertex_count(static_cast<std::uint32_t>(rest.vertices.rows()));
    u.header.set_face_count(static_cast<std::uint32_t>(rest.faces.rows()));
    u.faces.assign(rest.faces.data(), rest.faces.data() + rest.faces.size());
    u.shapes.emplace_back(rest.vertices.data(), rest.vertices.data() + rest.vertices.size());
    for (const auto& t : targets) {
      u.header.add_target_names(t.name);
      u.shapes.emplace_back(t.vertices.data(), t.vertices.data() + t.vertices.size());
    }
    return u;
  }
  std::vector<v1::UploadChunk> Chunks() const {
    std::vector<v1::UploadChunk> chunks(1);
    *chunks[0].mutable_header() = header;
    v1::UploadChunk faces_chunk;
    faces_chunk.mutable_piece()->set_kind(v1::MeshPiece::FACES);
    faces_chunk.mutable_piece()->set_data(faces.data(), faces.size() * sizeof(int));
    chunks.push_back(faces_chunk);
    for (size_t s = 0; s < shapes.size(); ++s) {
      v1::UploadChunk c;
      c.mutable_piece()->set_kind(v1::MeshPiece::POSITIONS);
      c.mutable_piece()->set_shape(static_cast<std::uint32_t>(s));
      c.mutable_piece()->set_data(shapes[s].data(), shapes[s].size() * sizeof(double));
      chunks.push_back(c);
    }
    chunks.insert(chunks.end(), extra.begin(), extra.end());
    return chunks;
  }
};

grpc::Status SendChunks(v1::CharacterService::Stub& stub, const std::vector<v1::UploadChunk>& chunks,
                        int cancel_after = -1) {
  auto context = Context();
  v1::Character response;
  auto writer = stub.UploadCharacter(context.get(), &response);
  for (size_t i = 0; i < chunks.size(); ++i) {
    if (static_cast<int>(i) == cancel_after) {
      context->TryCancel();
      break;
    }
    if (!writer->Write(chunks[i])) break;
  }
  if (cancel_after < 0) writer->WritesDone();
  return writer->Finish();
}

grpc::Status SendSolve(v1::SolveService::Stub& stub, const v1::SolveRequest& request) {
  auto context = Context();
  auto reader = stub.Solve(context.get(), request);
  v1::SolvedFrame frame;
  while (reader->Read(&frame)) {
  }
  return reader->Finish();
}

grpc::Status SendInteractive(v1::SolveService::Stub& stub, const std::vector<v1::InteractiveRequest>& messages) {
  auto context = Context();
  auto stream = stub.Interactive(context.get());
  for (const auto& m : messages) {
    if (!stream->Write(m)) break;
  }
  stream->WritesDone();
  v1::SolvedFrame frame;
  while (stream->Read(&frame)) {
  }
  return stream->Finish();
}

struct Case {
  std::string name;
  std::function<grpc::Status()> call;
  grpc::StatusCode code;
  std::string message;  // the answer's message must contain this
  std::string field;    // and this, when set: where the fault is
};

class BadInputTest : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = std::make_unique<ServerProcess>(
        cache_.path().string(),
        std::vector<std::string>{"--workers", "2", "--max-vertices", "50000", "--max-frames", "100"});
    ASSERT_FALSE(server_->address().empty()) << "the server did not start";
    channel_ = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
    characters_ = v1::CharacterService::NewStub(channel_);
    solves_ = v1::SolveService::NewStub(channel_);
  }

  std::vector<Case> Cases(const v1::Character& character, const Upload& good) {
    using grpc::StatusCode;
    std::vector<Case> cases;
    auto upload = [&](std::string name, std::function<void(Upload&)> breaks, StatusCode code, std::string message) {
      Upload u = good;
      breaks(u);
      cases.push_back({"upload: " + name, [this, u] { return SendChunks(*characters_, u.Chunks()); }, code, message});
    };
    auto chunks = [&](std::string name, std::vector<v1::UploadChunk> sent, StatusCode code, std::string message) {
      cases.push_back({"upload: " + name, [this, sent] { return SendChunks(*characters_, sent); }, code, message});
    };
    auto solve = [&](std::string name, std::function<void(v1::SolveRequest&)> breaks, StatusCode code,
                     std::string message) {
      v1::SolveRequest request = SweepRequest(character.id(), 2, {0.5, 0.5});
      breaks(request);
      cases.push_back({"solve: " + name, [this, request] { return SendSolve(*solves_, request); }, code, message});
    };
    auto collider = [&](std::string name, std::function<void(v1::Collider&)> shape, std::string message) {
      solve("collider " + name, [shape](v1::SolveRequest& r) { shape(*r.add_colliders()); },
            StatusCode::INVALID_ARGUMENT, message);
      cases.back().field = "colliders[0]";  // named once: "colliders[0]: ..." or "colliders[0].mesh_obj: ..."
    };
    auto interactive = [&](std::string name, std::vector<v1::InteractiveRequest> messages, StatusCode code,
                           std::string message) {
      cases.push_back({"interactive: " + name, [this, messages] { return SendInteractive(*solves_, messages); },
                       code, message});
    };
    const auto header_only = [&] {
      std::vector<v1::UploadChunk> h(1);
      *h[0].mutable_header() = good.header;
      return h;
    }();
    const StatusCode kInvalid = StatusCode::INVALID_ARGUMENT;

    // Uploads: empty, truncated, out of order, inconsistent.
    chunks("empty", {}, kInvalid, "without a header");
    chunks("header only", header_only, kInvalid, "face 0 missing");
    chunks("a piece first", {good.Chunks()[1]}, kInvalid, "before the header");
    chunks("neither header nor piece", {v1::UploadChunk()}, kInvalid, "neither header nor piece");
    upload("two headers", [](Upload& u) { u.extra.push_back(Upload(u).Chunks()[0]); }, kInvalid, "second upload header");
    upload("last target truncated", [](Upload& u) { u.shapes.back().resize(u.shapes.back().size() - 3); }, kInvalid,
           "vertex 1537 of shape 2 missing");
    upload("a piece of 7 bytes", [](Upload& u) {
      v1::UploadChunk c;
      c.mutable_piece()->set_kind(v1::MeshPiece::POSITIONS);
      c.mutable_piece()->set_data("1234567");
      u.extra.push_back(c);
    }, kInvalid, "not a multiple of 24");
    upload("a piece past the end", [](Upload& u) {
      v1::UploadChunk c;
      c.mutable_piece()->set_kind(v1::MeshPiece::FACES);
      c.mutable_piece()->set_offset(u.header.face_count());
      c.mutable_piece()->set_data(std::string(12, '\0'));
      u.extra.push_back(c);
    }, kInvalid, "covers elements");
    upload("overlapping pieces", [](Upload& u) { u.extra.push_back(u.Chunks()[2]); }, kInvalid, "overlap");
    upload("shape out of range", [](Upload& u) {
      v1::UploadChunk c;
      c.mutable_piece()->set_kind(v1::MeshPiece::POSITIONS);
      c.mutable_piece()->set_shape(7);
      u.extra.push_back(c);
    }, kInvalid, "piece.shape = 7");
    upload("unknown piece kind", [](Upload& u) {
      v1::UploadChunk c;
      c.mutable_piece()->set_kind(static_cast<v1::MeshPiece::Kind>(42));
      u.extra.push_back(c);
    }, kInvalid, "piece.kind");
    // Production rigs (header.targets, MASK pieces, in-betweens as further shapes).
    const auto production = [](Upload& u) {
      for (int t = 0; t < u.header.target_names_size(); ++t) u.header.add_targets();
    };
    const auto piece = [](Upload& u, v1::MeshPiece::Kind kind, std::uint32_t shape, size_t bytes) {
      v1::UploadChunk c;
      c.mutable_piece()->set_kind(kind);
      c.mutable_piece()->set_shape(shape);
      c.mutable_piece()->set_data(std::string(bytes, '\0'));
      u.extra.push_back(c);
    };
    upload("header.targets of the wrong count", [](Upload& u) { u.header.add_targets(); }, kInvalid,
           "header.targets has 1 entries");
    upload("a MASK piece for a target without a mask", [&](Upload& u) {
      production(u);
      piece(u, v1::MeshPiece::MASK, 0, 8 * u.header.vertex_count());
    }, kInvalid, "does not give a mask");
    upload("a mask never sent", [&](Upload& u) {
      production(u);
      u.header.mutable_targets(1)->set_has_mask(true);
    }, kInvalid, "value 0 of target 1's mask missing");
    upload("a MASK piece of 7 bytes", [&](Upload& u) {
      production(u);
      u.header.mutable_targets(0)->set_has_mask(true);
      piece(u, v1::MeshPiece::MASK, 0, 7);
    }, kInvalid, "not a multiple of 8");
    upload("an in-between never sent", [&](Upload& u) {
      production(u);
      u.header.mutable_targets(0)->add_inbetween_weights(0.5);
    }, kInvalid, "of shape 3 missing");
    upload("an in-between weight of 1.5", [&](Upload& u) {
      production(u);
      u.header.mutable_targets(0)->add_inbetween_weights(1.5);
      u.shapes.push_back(u.shapes[1]);
    }, kInvalid, "header.targets[0] (target 'poses-2_cube-1'): inbetween_weights[0] = 1.5 is outside (0, 1)");
    upload("a combination of an unknown target", [&](Upload& u) {
      production(u);
      u.header.mutable_targets(1)->add_combination(u.header.target_names(0));
      u.header.mutable_targets(1)->add_combination("nobody");
    }, kInvalid, "nobody");
    // The header's counts and names.
    upload("2 vertices", [](Upload& u) { u.header.set_vertex_count(2); }, kInvalid, "at least 3 vertices");
    upload("no faces", [](Upload& u) { u.header.set_face_count(0); }, kInvalid, "face_count = 0");
    upload("no targets", [](Upload& u) { u.header.clear_target_names(); }, kInvalid, "target_names is empty");
    upload("duplicate target names", [](Upload& u) { u.header.set_target_names(1, u.header.target_names(0)); },
           kInvalid, "used twice");
    upload("an empty target name", [](Upload& u) { u.header.set_target_names(0, ""); }, kInvalid,
           "target_names[0] is empty");
    upload("a 300-byte name", [](Upload& u) { u.header.set_name(std::string(300, 'n')); }, kInvalid,
           "longer than 256 bytes");
    upload("4 billion vertices", [](Upload& u) { u.header.set_vertex_count(4'000'000'000u); },
           StatusCode::RESOURCE_EXHAUSTED, "--max-vertices");
    upload("4 billion faces", [](Upload& u) { u.header.set_face_count(4'000'000'000u); },
           StatusCode::RESOURCE_EXHAUSTED, "over the limit");
    upload("5000 targets", [](Upload& u) {
      for (int t = 0; t < 5000; ++t) u.header.add_target_names(fmt::format("t{}", t));
    }, StatusCode::RESOURCE_EXHAUSTED, "over the limit of 1000");
    upload("a fixed vertex out of range", [](Upload& u) { u.header.mutable_options()->add_fixed_vertices(1u << 30); },
           kInvalid, "options.fixed_vertices");
    upload("a NaN bending stiffness", [](Upload& u) { u.header.mutable_options()->set_bending_stiffness(kNaN); },
           kInvalid, "bending");
    upload("100000 path steps per unit", [](Upload& u) { u.header.mutable_options()->set_path_intervals(100000); },
           kInvalid, "options.path_intervals = 100000 is outside [4, 128]");
    upload("2 path samples", [](Upload& u) { u.header.mutable_options()->set_path_max_samples(2); }, kInvalid,
           "options.path_max_samples = 2 is outside [8, 256]");
    // The meshes themselves.
    upload("a NaN rest coordinate", [](Upload& u) { u.shapes[0][4] = kNaN; }, kInvalid,
           "rest mesh: vertex 1 has a non-finite y coordinate");
    upload("an infinite target coordinate", [](Upload& u) { u.shapes[2][0] = -kInf; }, kInvalid,
           "vertex 0 has a non-finite x coordinate");
    upload("a negative face index", [](Upload& u) { u.faces[5] = -1; }, kInvalid, "face 1 refers to vertex -1");
    upload("a face index out of range", [](Upload& u) { u.faces[0] = 1 << 20; }, kInvalid,
           "face 0 refers to vertex 1048576");
    upload("a face repeating a vertex", [](Upload& u) { u.faces[1] = u.faces[0]; }, kInvalid, "repeats a vertex");
    upload("all vertices in one point", [](Upload& u) {
      for (auto& s : u.shapes) std::fill(s.begin(), s.end(), 1.0);
    }, kInvalid, "coincide");
    // Mismatched topology goes through the client library, which refuses it before sending.
    cases.push_back({"upload: a target with other faces (client library)", [this] {
      CylinderRig cylinder;
      std::swap(cylinder.targets[1].faces(7, 0), cylinder.targets[1].faces(7, 1));
      try {
        Client({server_->address()}).Upload(cylinder.rest, cylinder.targets);
      } catch (const ClientError& e) {
        return grpc::Status(static_cast<grpc::StatusCode>(e.code()), e.what());
      }
      return grpc::Status::OK;
    }, kInvalid, "face 7 differs"});
    cases.push_back({"upload: cancelled halfway", [this, good] { return SendChunks(*characters_, good.Chunks(), 3); },
                     StatusCode::CANCELLED, ""});

    // Solves.
    solve("unknown character", [](v1::SolveRequest& r) { r.set_character_id(std::string(64, 'a')); },
          StatusCode::NOT_FOUND, "upload it first");
    // An id that is not a hex digest is a malformed request (issue 19), never a path.
    solve("a path as the id", [](v1::SolveRequest& r) { r.set_character_id("../../../../etc/passwd"); },
          kInvalid, "is not a character id");
    solve("a 64-character path as the id", [](v1::SolveRequest& r) { r.set_character_id("/" + std::string(63, 'a')); },
          kInvalid, "is not a character id");
    solve("an empty id", [](v1::SolveRequest& r) { r.clear_character_id(); }, kInvalid, "is not a character id");
    solve("no frames", [](v1::SolveRequest& r) { r.clear_frames(); }, kInvalid, "frames is empty");
    solve("101 frames", [](v1::SolveRequest& r) {
      for (int i = 0; i < 99; ++i) *r.add_frames() = r.frames(0);
    }, StatusCode::RESOURCE_EXHAUSTED, "over the limit of 100 (--max-frames)");
    solve("one weight for two targets", [](v1::SolveRequest& r) { r.mutable_frames(1)->mutable_weights()->RemoveLast(); },
          kInvalid, "frames[1]: weights has 1 entries but the rig has 2 targets");
    solve("three weights", [](v1::SolveRequest& r) { r.mutable_frames(0)->add_weights(0); }, kInvalid,
          "weights has 3 entries");
    solve("no weights", [](v1::SolveRequest& r) { r.mutable_frames(0)->clear_weights(); }, kInvalid,
          "weights has 0 entries");
    solve("a NaN weight", [](v1::SolveRequest& r) { r.mutable_frames(1)->set_weights(0, kNaN); }, kInvalid,
          "frames[1]: weights[0]");
    solve("an infinite weight", [](v1::SolveRequest& r) { r.mutable_frames(0)->set_weights(1, kInf); }, kInvalid,
          "is not finite");
    solve("a pin past the last vertex", [](v1::SolveRequest& r) { r.mutable_frames(0)->add_pins()->set_vertex(100000); },
          kInvalid, "vertex 100000");
    solve("a pin at vertex 2^32-1 (a negative index)", [](v1::SolveRequest& r) {
      r.mutable_frames(0)->add_pins()->set_vertex(0xffffffffu);
    }, kInvalid, "vertex 4294967295");
    solve("a pin at NaN", [](v1::SolveRequest& r) {
      r.mutable_frames(0)->add_pins()->mutable_position()->set_x(kNaN);
    }, kInvalid, "non-finite position");
    solve("a NaN tolerance", [](v1::SolveRequest& r) { r.mutable_options()->set_residual_tolerance(kNaN); }, kInvalid,
          "options:");
    solve("a negative tolerance", [](v1::SolveRequest& r) { r.mutable_options()->set_residual_tolerance(-1); },
          kInvalid, "options:");
    solve("a transform for a missing collider", [](v1::SolveRequest& r) { r.mutable_frames(0)->add_collider_transforms(); },
          kInvalid, "collider_transforms has 1 entries but there are 0 colliders");
    solve("a NaN collider translation", [](v1::SolveRequest& r) {
      r.add_colliders()->mutable_plane()->mutable_normal()->set_z(1);
      r.mutable_frames(0)->add_collider_transforms()->mutable_translation()->set_y(kNaN);
    }, kInvalid, "collider_transforms[0] is not a finite rigid transform");
    solve("a NaN quaternion", [](v1::SolveRequest& r) {
      r.add_colliders()->mutable_plane()->mutable_normal()->set_z(1);
      r.mutable_frames(0)->add_collider_transforms()->set_qw(kNaN);
    }, kInvalid, "not a finite quaternion");
    collider("without a shape", [](v1::Collider&) {}, "no shape set");
    collider("sphere of radius 0", [](v1::Collider& c) { c.mutable_sphere()->set_radius(0); }, "radius > 0");
    collider("sphere of negative radius", [](v1::Collider& c) { c.mutable_sphere()->set_radius(-1); }, "radius > 0");
    collider("sphere at NaN", [](v1::Collider& c) {
      c.mutable_sphere()->set_radius(1);
      c.mutable_sphere()->mutable_center()->set_x(kNaN);
    }, "finite centre");
    collider("capsule of radius 0", [](v1::Collider& c) { c.mutable_capsule()->mutable_b()->set_x(1); }, "radius > 0");
    collider("capsule of infinite end", [](v1::Collider& c) {
      c.mutable_capsule()->set_radius(1);
      c.mutable_capsule()->mutable_a()->set_z(kInf);
    }, "finite end points");
    collider("flat box", [](v1::Collider& c) {
      c.mutable_box()->mutable_half_extents()->set_x(1);
      c.mutable_box()->mutable_half_extents()->set_y(1);
    }, "half extents > 0");
    collider("plane without a normal", [](v1::Collider& c) { c.mutable_plane(); }, "non-zero normal");
    collider("empty mesh", [](v1::Collider& c) { c.set_mesh_obj(""); }, "mesh_obj: the mesh has no vertices");
    collider("mesh of garbage", [](v1::Collider& c) { c.set_mesh_obj("this is not an OBJ file\n\x01\x02"); }, "mesh_obj: ");
    collider("open mesh", [](v1::Collider& c) { c.set_mesh_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"); }, "closed");
    collider("mesh with a face past its vertices", [](v1::Collider& c) {
      c.set_mesh_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 9\n");
    }, "mesh_obj: face 1 refers to vertex 8");
    // A fuzzer finding: OpenMesh's OBJ reader aborted the process on a face corner without a vertex index.
    collider("mesh with a face corner without a vertex", [](v1::Collider& c) {
      c.set_mesh_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf /2 3 1\n");
    }, "mesh_obj: line 5: face corner '/2'");
    collider("mesh with a NaN vertex", [](v1::Collider& c) {
      c.set_mesh_obj("v 0 0 0\nv 1 0 nan\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n");
    }, "mesh");

    // Unknown fields are ignored (proto3: a newer client talking to an older server still works).
    solve("unknown fields (ignored)", [](v1::SolveRequest& r) {
      r.GetReflection()->MutableUnknownFields(&r)->AddVarint(999, 7);
      r.mutable_frames(0)->GetReflection()->MutableUnknownFields(r.mutable_frames(0))->AddLengthDelimited(77, "x");
    }, StatusCode::OK, "");

    // Interactive sessions.
    v1::InteractiveRequest start, frame, wrong_frame, unknown_start;
    start.mutable_start()->set_character_id(character.id());
    frame.mutable_frame()->add_weights(0.5);
    frame.mutable_frame()->add_weights(0.5);
    wrong_frame.mutable_frame()->add_weights(kNaN);
    unknown_start.mutable_start()->set_character_id(std::string(64, 'f'));
    interactive("a frame first", {frame}, kInvalid, "the first message must be a start message");
    interactive("two starts", {start, start}, kInvalid, "only the first message");
    interactive("an unknown character", {unknown_start, frame}, StatusCode::NOT_FOUND, "upload it first");
    interactive("a bad frame", {start, wrong_frame}, kInvalid, "weights has 1 entries");
    interactive("an empty session", {}, StatusCode::OK, "");

    // Other calls.
    cases.push_back({"get: a path", [this] {
      v1::GetCharacterRequest r;
      r.set_id("../" + std::string(61, 'a'));
      v1::Character out;
      return characters_->GetCharacter(Context().get(), r, &out);
    }, kInvalid, "is not a character id"});
    cases.push_back({"delete: a path", [this] {
      v1::DeleteCharacterRequest r;
      r.set_id(cache_.path().string() + "/../x");
      v1::DeleteCharacterResponse out;
      return characters_->DeleteCharacter(Context().get(), r, &out);
    }, kInvalid, "is not a character id"});
    return cases;
  }

  TempDir cache_;
  std::unique_ptr<ServerProcess> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::CharacterService::Stub> characters_;
  std::unique_ptr<v1::SolveService::Stub> solves_;
};

std::set<std::string> FilesIn(const std::filesystem::path& dir) {
  std::set<std::string> names;
  for (const auto& f : std::filesystem::directory_iterator(dir)) names.insert(f.path().filename().string());
  return names;
}

TEST_F(BadInputTest, EveryMalformedRequestGetsTheRightStatusWhileAHealthyClientIsServed) {
  CylinderRig cylinder;
  Client client({server_->address()});
  const v1::Character c = client.Upload(cylinder.rest, cylinder.targets, {}, "cylinder");
  const auto files_before = FilesIn(cache_.path());
  const v1::SolveRequest healthy_request = SweepRequest(c.id(), 3, {0.8, 0.3});
  std::vector<Points> reference;
  client.Solve(healthy_request, [&](const v1::SolvedFrame& f) { reference.push_back(Client::Decode(f.positions())); });
  ASSERT_EQ(reference.size(), 3u);
  const double tolerance = 1e-9 * BoundingBoxDiagonal(cylinder.rest.vertices);

  // The healthy client solves the same sweep over and over while the bad requests go in.
  std::atomic<bool> stop{false};
  std::atomic<int> healthy_rounds{0}, healthy_failures{0};
  std::thread healthy([&] {
    Client own({server_->address()});
    while (!stop) {
      try {
        std::vector<Points> frames;
        own.Solve(healthy_request, [&](const v1::SolvedFrame& f) { frames.push_back(Client::Decode(f.positions())); });
        bool same = frames.size() == reference.size();
        for (size_t i = 0; same && i < frames.size(); ++i) same = testing::MaxDistance(frames[i], reference[i]) <= tolerance;
        (same ? healthy_rounds : healthy_failures)++;
      } catch (const ClientError&) {
        healthy_failures++;
      }
    }
  });

  const Upload good = Upload::Of(LoadMesh(testing::DataPath("cube/cube.obj")),
                                 {LoadMesh(testing::DataPath("cube/poses-2_cube-1.obj")),
                                  LoadMesh(testing::DataPath("cube/poses-1_cube-2.obj"))});
  const std::vector<Case> cases = Cases(c, good);
  for (const Case& bad : cases) {
    const grpc::Status status = bad.call();
    EXPECT_EQ(status.error_code(), bad.code) << bad.name << ": " << status.error_message();
    EXPECT_THAT(status.error_message(), ::testing::HasSubstr(bad.message)) << bad.name;
    EXPECT_THAT(status.error_message(), ::testing::HasSubstr(bad.field)) << bad.name;
    if (bad.code != grpc::StatusCode::OK && bad.code != grpc::StatusCode::CANCELLED) {
      EXPECT_FALSE(status.error_message().empty()) << bad.name;
    }
  }
  // Let the healthy client finish at least two sweeps alongside.
  while (healthy_rounds < 2 && healthy_failures == 0) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  stop = true;
  healthy.join();
  EXPECT_EQ(healthy_failures, 0);
  EXPECT_GE(healthy_rounds, 2);
  std::cout << cases.size() << " bad requests; the healthy client solved " << healthy_rounds << " sweeps meanwhile\n";

  // Nothing cached changed: the same one character, the same files, the same rig.
  const auto listed = client.List();
  ASSERT_EQ(listed.size(), 1u);
  EXPECT_EQ(listed[0].id(), c.id());
  EXPECT_EQ(client.Get(c.id()).summary().springs(), c.summary().springs());
  EXPECT_EQ(FilesIn(cache_.path()), files_before);
  EXPECT_TRUE(client.Healthy());
}

}  // namespace
}  // namespace springblend
