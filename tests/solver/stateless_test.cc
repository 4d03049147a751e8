// Stateless frames: a frame's answer is a function of its own weights, whatever was solved before it on the
// same solver. Alpha 0.5 reached as frame 18 of a 37-step sweep, alone, and right after alpha 1 agree, on the
// bundled rigs always and on the production meshes of ../shared when present; random multi-target frames (the
// cube's poses, the five-expression face) agree in any order; every frame converges.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <random>

#include "test_util.h"

namespace springblend {
namespace {

using testing::DataPath;
using testing::MaxDistance;

constexpr double kAgreement = 1e-5;  // of the bounding-box diagonal

struct StatelessCase {
  const char* name;
  bool shared;  // in ../shared/meshes (skipped when absent) rather than tests/data
  const char* rest;
  std::vector<const char*> targets;
  std::vector<double> end;  // the sweep's last weights
};

// Readable in ctest's output (gtest prints a parameter without PrintTo as raw bytes).
void PrintTo(const StatelessCase& c, std::ostream* os) { *os << std::string(c.name) + " (" + c.rest + ")"; }

std::string PathOf(const StatelessCase& c, const char* file) {
  return c.shared ? std::string(SPRINGBLEND_SHARED_MESHES) + "/" + file : DataPath(file);
}

std::shared_ptr<const Rig> Build(const StatelessCase& c) {
  std::vector<TriangleMesh> targets;
  for (const char* t : c.targets) targets.push_back(LoadMesh(PathOf(c, t)));
  // What is checked (a frame's answer depends on its request alone) does not depend on how densely the paths
  // are swept (solver_target_paths_test checks the default's paths): 8 steps per unit bound CI's time on the
  // face, horse and cat.
  const RigOptions options = testing::TestRigOptions();
  return Rig::Build(LoadMesh(PathOf(c, c.rest)), std::move(targets), options);
}

Points SolveOrFail(Solver& solver, const std::vector<double>& weights, const std::string& what, int* newton = nullptr) {
  Points x;
  const SolveSummary s = solver.Solve(Frame{weights}, &x);
  EXPECT_TRUE(s.converged()) << what << ": " << ToString(s.termination) << " " << s.message;
  if (newton != nullptr) *newton = s.newton_iterations;
  return x;
}

class Stateless : public ::testing::TestWithParam<StatelessCase> {};

TEST_P(Stateless, HalfwayIsTheSameAloneInASweepAndAfterTheTarget) {
  const StatelessCase& c = GetParam();
  if (c.shared && !std::filesystem::exists(PathOf(c, c.rest))) {
    GTEST_SKIP() << SPRINGBLEND_SHARED_MESHES << " is absent (it is not part of the repository)";
  }
  const auto rig = Build(c);
  const double diagonal = rig->summary().bounding_box_diagonal;
  EXPECT_EQ(rig->summary().unconverged_path_samples, 0) << "every sample of the targets' paths converges";
  const std::vector<Frame> sweep = SweepFrames(c.end, 37);
  ASSERT_DOUBLE_EQ(sweep[18].weights[0], 0.5 * c.end[0]);

  // The sweep's frames on one solver, up to frame 18 (every frame on the small rigs; a walk through the sweep
  // on the large ones, whose frames cost seconds each).
  Solver in_sweep(rig);
  Points swept;
  const int stride = rig->num_vertices() < 5000 ? 1 : 6;
  for (int i = 0; i <= 18; i += (i + stride <= 18 || i == 18) ? stride : 18 - i) {
    swept = SolveOrFail(in_sweep, sweep[i].weights, "sweep frame " + std::to_string(i));
    if (i == 18) break;
  }
  Solver alone_solver(rig);
  int newton_alone = 0;
  const Points alone = SolveOrFail(alone_solver, sweep[18].weights, "alone", &newton_alone);
  Solver back(rig);
  SolveOrFail(back, c.end, "the target");
  const Points after_target = SolveOrFail(back, sweep[18].weights, "after the target");

  EXPECT_LE(MaxDistance(swept, alone), kAgreement * diagonal);
  EXPECT_LE(MaxDistance(after_target, alone), kAgreement * diagonal);
  if (c.targets.size() > 1) {
    // A few random multi-target frames solved forwards, backwards and alone agree too.
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> weight(0.0, 0.6);
    std::vector<std::vector<double>> frames(2, std::vector<double>(c.targets.size()));
    for (auto& w : frames) {
      for (double& v : w) v = weight(rng);
    }
    Solver forwards(rig), backwards(rig);
    const Points a0 = SolveOrFail(forwards, frames[0], "random frame 0, forwards");
    const Points a1 = SolveOrFail(forwards, frames[1], "random frame 1, forwards");
    const Points b1 = SolveOrFail(backwards, frames[1], "random frame 1, backwards");
    const Points b0 = SolveOrFail(backwards, frames[0], "random frame 0, backwards");
    EXPECT_LE(MaxDistance(a0, b0), kAgreement * diagonal);
    EXPECT_LE(MaxDistance(a1, b1), kAgreement * diagonal);
  }
  RecordProperty("newton_alone", newton_alone);
  if (c.end.size() == 1 && c.end[0] == 1.0) {
    // Halfway is a sample of the target's path: the frame starts at its answer.
    EXPECT_LE(newton_alone, 3);
  }
}

INSTANTIATE_TEST_SUITE_P(
    Rigs, Stateless,
    ::testing::Values(
        StatelessCase{"cylinder", false, "cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, {1.0}},
        StatelessCase{"cube", false, "cube/cube.obj", {"cube/poses-1_cube-4.obj"}, {1.0}},
        StatelessCase{"cheburashka", false, "cheburashka/cheburashka.obj", {"cheburashka/poses-1_cheburashka-1.obj"},
                      {1.0}},
        StatelessCase{"face_jawOpen", false, "face/generic_neutral_mesh.obj", {"face/jawOpen.obj"}, {1.0}},
        StatelessCase{"shared_face_mix", true, "face6706/generic_neutral_mesh.obj",
                      {"face6706/jawOpen.obj", "face6706/mouthSmile_L.obj", "face6706/mouthSmile_R.obj",
                       "face6706/eyeBlink_L.obj", "face6706/browInnerUp_L.obj"},
                      {0.6, 0.5, 0.5, 0.8, 0.7}},
        StatelessCase{"shared_horse", true, "horse/horse-reference.obj", {"horse/horse-01.obj"}, {1.0}},
        StatelessCase{"shared_cat", true, "cat/cat-reference.obj", {"cat/cat-01.obj"}, {1.0}}),
    [](const ::testing::TestParamInfo<StatelessCase>& param) { return std::string(param.param.name); });

TEST(Stateless, MultiTargetFramesAgreeInAnyOrder) {
  // Four cube poses driven together: random frames solved forwards, backwards and one at a time.
  const auto rig = testing::LoadRig("cube/cube.obj", {"cube/poses-1_cube-1.obj", "cube/poses-1_cube-2.obj",
                                                      "cube/poses-1_cube-3.obj", "cube/poses-1_cube-4.obj"});
  std::mt19937 rng(2024);
  std::uniform_real_distribution<double> weight(0.0, 0.6);
  std::vector<std::vector<double>> frames(5);
  for (auto& w : frames) {
    for (int t = 0; t < 4; ++t) w.push_back(weight(rng));
  }
  Solver forwards(rig), backwards(rig);
  std::vector<Points> ahead(frames.size()), behind(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) ahead[i] = SolveOrFail(forwards, frames[i], "forwards");
  for (size_t i = frames.size(); i-- > 0;) behind[i] = SolveOrFail(backwards, frames[i], "backwards");
  for (size_t i = 0; i < frames.size(); ++i) {
    Solver alone(rig);
    const Points x = SolveOrFail(alone, frames[i], "alone");
    EXPECT_LE(MaxDistance(ahead[i], x), kAgreement * rig->summary().bounding_box_diagonal) << "frame " << i;
    EXPECT_LE(MaxDistance(behind[i], x), kAgreement * rig->summary().bounding_box_diagonal) << "frame " << i;
  }
}

TEST(Stateless, TheStartOfAFrameIsTheRigsPredictionForItsWeights) {
  const auto rig = testing::LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  Solver solver(rig);
  const Points before = solver.Start({0.3});
  SolveOrFail(solver, {0.9}, "another frame");
  EXPECT_EQ(solver.Start({0.3}), before);
  // The paths make the start far closer to the answer than the linear blend is.
  Points answer;
  ASSERT_TRUE(solver.Solve(Frame{{0.3}}, &answer).converged());
  const Points linear = LinearBlend(*rig, {0.3});
  const double from_path = MaxDistance(before.topRows(rig->num_surface_vertices()), answer);
  const double from_linear = MaxDistance(linear, answer);
  RecordProperty("start_error_path", std::to_string(from_path));
  RecordProperty("start_error_linear", std::to_string(from_linear));
  EXPECT_LT(from_path, 0.1 * from_linear);
}

TEST(Stateless, WithoutTargetPathsFramesAreStillIndependent) {
  RigOptions no_paths;
  no_paths.target_paths = false;
  const auto rig = testing::LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, no_paths);
  EXPECT_EQ(rig->summary().path_samples, 0);
  Solver alone(rig), after(rig);
  const Points x = SolveOrFail(alone, {0.5}, "alone");
  SolveOrFail(after, {1.0}, "the target");
  EXPECT_EQ(SolveOrFail(after, {0.5}, "after the target"), x);
}

}  // namespace
}  // namespace springblend
