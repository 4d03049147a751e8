// The one conversion layer between springblend.v1 messages and solver types.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "character_store.h"
#include "memory_budget.h"
#include "springblend/collider.h"
#include "springblend/solve.h"
#include "springblend/v1/springblend.pb.h"

namespace springblend::server {

struct Limits {
  std::int64_t max_upload_bytes = 512LL << 20;
  int max_vertices = 2'000'000;
  int max_targets = 1000;
  int max_frames = 100'000;
  size_t max_name_bytes = 256;  // a character's name and each target name
  int max_colliders = 64;
  // A mesh collider's OBJ text (checked in a linear pass before OpenMesh) and the mesh (before CGAL).
  MeshTextLimits collider_text{100'000, 200'000, 256, 256};
  MeshColliderLimits collider{100'000, 200'000, 256};

  // --max-collider-faces: one cap on a mesh collider's triangles and vertices, as OBJ text and as arrays.
  void SetMaxColliderFaces(int faces) {
    collider.max_faces = collider.max_vertices = faces;
    collider_text.max_faces = collider_text.max_vertices = faces;
  }
};

// Collects an upload's chunks, checking each against the header and the limits as it arrives. Memory grows as
// pieces arrive (counted in `budget`), never from what the header declares.
class UploadAssembler {
 public:
  explicit UploadAssembler(Limits limits, MemoryBudget* budget = nullptr) : limits_(limits), memory_(budget) {}
  // Throws Error(kInvalidInput) naming the problem, LimitError over a limit. Takes the piece's bytes.
  void Add(v1::UploadChunk& chunk);
  // Throws if a mesh is incomplete.
  CharacterData Finish();

 private:
  [[noreturn]] void Fail(const std::string& what, bool limit = false);

  Limits limits_;
  Reservation memory_;
  bool have_header_ = false;
  std::int64_t bytes_ = 0;
  CharacterData data_;
  std::uint32_t vertex_count_ = 0, face_count_ = 0;
  size_t shapes_ = 0;                       // POSITIONS arrays: rest, targets, in-betweens
  std::vector<std::uint32_t> mask_owner_;   // per MASK array, its target
  struct Piece {
    size_t array;  // 0 faces, 1 + s shape s, then 1 + shapes_ + k the k-th mask
    size_t offset;
    std::string bytes;
  };
  std::vector<Piece> pieces_;
  std::vector<std::map<size_t, size_t>> covered_;  // per array: disjoint [first, end) ranges that arrived
};

// A character id from a request, checked: 64 lowercase hex digits, else Error(kInvalidInput) quoting at most
// its start.
void CheckId(const std::string& id, const char* field);
// Text from a client made safe for a log line or a message: control bytes and backslashes escaped, cut to
// `max` bytes.
std::string Printable(std::string_view text, size_t max = 64);

v1::Character ToProto(const CharacterStore::Entry& entry, bool cache_hit);  // READY, with the summary
v1::Character ToProto(const CharacterStore::PendingBuild& build);          // BUILDING, with its progress

// A solve request turned into solver input; throws Error(kInvalidInput) naming the field (frames[3].weights).
struct SolveJob {
  std::vector<Frame> frames;
  std::vector<Collider> colliders;
  SolveOptions options;
  bool with_normals = false;
};
SolveJob ToSolveJob(const v1::SolveRequest& request, const Rig& rig, const Limits& limits,
                    const std::function<bool()>& stopped = {});
// The parts of it, for Interactive (colliders and options once at the start, then each frame by itself).
// `stopped`, when given, is asked before each collider and each frame: true throws CancelledError.
std::vector<Collider> ToColliders(const google::protobuf::RepeatedPtrField<v1::Collider>& colliders,
                                  const Limits& limits, const std::function<bool()>& stopped = {});
void ToOptions(const v1::SolveOptions& options, SolveJob* job);
// `index` names the frame in messages: frames[index].
Frame ToFrame(const v1::FrameRequest& request, const Rig& rig, size_t colliders, size_t index);
// Throws Error(kNumerical) naming the frame when a solve returned non-finite positions.
void CheckSolved(const Points& positions, size_t index);
// What a stream with these colliders holds while open (the converted colliders), for the memory budget; each of
// its Solvers is counted apart (Solver::bytes).
std::int64_t StreamBytes(const google::protobuf::RepeatedPtrField<v1::Collider>& colliders);
// What a parsed Solve request holds in memory (its messages, their repeated fields), from its counts, for the
// memory budget: several times its bytes on the wire for a request of pins.
std::int64_t RequestBytes(const v1::SolveRequest& request);
// What a frame holds once converted (ToFrame): the same from the request's counts, or from the frame.
std::int64_t FrameBytes(const v1::FrameRequest& frame);
std::int64_t FrameBytes(const Frame& frame);

v1::SolvedFrame ToProto(int index, const Points& positions, const Faces& faces, const SolveSummary& summary,
                        bool with_normals, const std::string& served_by);

}  // namespace springblend::server
