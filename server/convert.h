// The one conversion layer between springblend.v1 messages and solver types.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "character_store.h"
#include "springblend/solve.h"
#include "springblend/v1/springblend.pb.h"

namespace springblend::server {

struct Limits {
  std::int64_t max_upload_bytes = 512LL << 20;
  int max_vertices = 2'000'000;
  int max_targets = 1000;
  int max_frames = 100'000;
};

// Collects an upload's chunks, checking each against the header and the limits as it arrives.
class UploadAssembler {
 public:
  explicit UploadAssembler(Limits limits) : limits_(limits) {}
  // Throws Error(kInvalidInput) naming the problem; a limit exceeded says so ("over the limit").
  void Add(const v1::UploadChunk& chunk);
  // Throws if a mesh is incomplete.
  CharacterData Finish();
  bool over_limit() const { return over_limit_; }

 private:
  void Fail(const std::string& what, bool limit = false);

  Limits limits_;
  bool have_header_ = false;
  bool over_limit_ = false;
  std::int64_t bytes_ = 0;
  CharacterData data_;
  std::vector<std::vector<char>> filled_;  // per array (faces, then shapes): which elements arrived
};

v1::Character ToProto(const CharacterStore::Entry& entry, bool cache_hit);

// A solve request turned into solver input; throws Error(kInvalidInput) naming the field (frames[3].weights).
struct SolveJob {
  std::vector<Frame> frames;
  std::vector<Collider> colliders;
  SolveOptions options;
  bool with_normals = false;
};
SolveJob ToSolveJob(const v1::SolveRequest& request, const Rig& rig, const Limits& limits);

v1::SolvedFrame ToProto(int index, const Points& positions, const Faces& faces, const SolveSummary& summary,
                        bool with_normals, const std::string& served_by);

}  // namespace springblend::server
