// libFuzzer target: request validation. The input is a serialized SolveRequest, checked against a small
// two-target rig by ToSolveJob (frames, weights, pins, colliders, options, mesh colliders' OBJ text).
#include <cstddef>
#include <cstdint>
#include <memory>

#include "convert.h"
#include "status.h"
#include "springblend/error.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"

namespace {

// A tetrahedron and two targets: the smallest closed rig.
std::shared_ptr<const springblend::Rig> SmallRig() {
  const char* rest = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n";
  springblend::TriangleMesh r = springblend::LoadMeshFromText(rest, "obj", "rest");
  springblend::TriangleMesh a = r, b = r;
  a.name = "a";
  b.name = "b";
  a.vertices(3, 2) = 1.5;
  b.vertices(1, 0) = 0.7;
  return springblend::Rig::Build(r, {a, b});
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  static const std::shared_ptr<const springblend::Rig> rig = SmallRig();
  springblend::v1::SolveRequest request;
  if (!request.ParseFromArray(data, static_cast<int>(size))) return 0;
  springblend::server::Limits limits;
  limits.max_frames = 64;
  try {
    springblend::server::ToSolveJob(request, *rig, limits);
  } catch (const springblend::Error&) {
  } catch (const springblend::server::LimitError&) {  // over a limit: RESOURCE_EXHAUSTED, a refusal too
  }
  return 0;
}
