// The production meshes of ../shared/meshes that may not be copied into the repository (the horse and cat
// of Sumner and Popovic, and the open ICT face): each builds a rig, or falls back on purpose, without
// crashing. Skips when ../shared is absent (a user's fresh clone).
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>

#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;

struct SharedCase {
  const char* name;
  const char* rest;
  const char* target;
  const char* interior;           // the path the rig builder must take
  const char* reason_substring;  // and the reason it gives
};

// Readable in ctest's output (gtest prints a parameter without PrintTo as raw bytes).
void PrintTo(const SharedCase& c, std::ostream* os) { *os << std::string(c.name) + " (" + c.rest + ", " + c.target + ")"; }

class SharedMeshes : public ::testing::TestWithParam<SharedCase> {};

TEST_P(SharedMeshes, BuildARigOrFallBackWithTheDocumentedReason) {
  const std::string root = SPRINGBLEND_SHARED_MESHES;
  if (!std::filesystem::exists(root + "/" + GetParam().rest)) {
    GTEST_SKIP() << root << " is absent (it is not part of the repository)";
  }
  // The build's interior path is what is checked here; the target paths are solver_stateless_test's.
  RigOptions options;
  options.target_paths = false;
  auto rig = Rig::Build(LoadMesh(root + "/" + GetParam().rest), {LoadMesh(root + "/" + GetParam().target)}, options);
  const RigSummary& s = rig->summary();
  EXPECT_EQ(s.interior, GetParam().interior) << s.interior_reason;
  EXPECT_THAT(s.interior_reason, HasSubstr(GetParam().reason_substring));
  RecordProperty("vertices", s.vertices);
  RecordProperty("springs", s.springs);
  RecordProperty("tetrahedra", s.tetrahedra);
  RecordProperty("precompute_ms", std::to_string(s.precompute_ms));
  // The rest shape is an equilibrium of the built rig; the target is reproduced exactly.
  for (double w : {0.0, 1.0}) {
    Solver solver(rig);
    Points x;
    const SolveSummary summary = solver.Solve({{w}}, &x);
    ASSERT_TRUE(summary.converged()) << summary.message;
    EXPECT_LE(testing::MaxDistance(x, w == 0.0 ? rig->rest().vertices : rig->target(0).vertices),
              1e-6 * s.bounding_box_diagonal);
  }
}

INSTANTIATE_TEST_SUITE_P(
    ProductionMeshes, SharedMeshes,
    ::testing::Values(
        // A 19-edge slit in one hoof (and a second, small hole): capped, then tetrahedralized.
        SharedCase{"horse", "horse/horse-reference.obj", "horse/horse-01.obj", "capped", "holes closed"},
        // About 200 self-intersecting triangle pairs: TetGen refuses; a shell (inner layer), and why.
        SharedCase{"cat", "cat/cat-reference.obj", "cat/cat-01.obj", "shell", "intersects itself"},
        // An open mask (rim, mouth, eyes): its caps cut through the face; a shell (inner layer), and why.
        SharedCase{"face", "face6706/generic_neutral_mesh.obj", "face6706/jawOpen.obj", "shell",
                   "inner layer"}),
    [](const ::testing::TestParamInfo<SharedCase>& param) { return std::string(param.param.name); });

}  // namespace
}  // namespace springblend
