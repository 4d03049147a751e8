// The per-frame solve on the bundled meshes: exact reproduction of the shapes, equilibrium residuals,
// the physical advantage over linear blending, sweeps, backends and refusals.
#include "springblend/solve.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <malloc.h>

#include <algorithm>
#include <cmath>
#include <thread>

#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CatchError;
using testing::LoadRig;
using testing::MaxDistance;

constexpr double kShapeTolerance = 1e-6;  // of the bounding-box diagonal

double Diagonal(const Rig& rig) { return rig.summary().bounding_box_diagonal; }

// Mean relative deviation |l - r̄| / r̄ of the structure springs (mesh edges) of `x`.
double EdgeLengthError(const Rig& rig, const Points& x, const std::vector<double>& weights) {
  std::vector<double> blended;
  BlendRestLengths(rig, weights, &blended);
  double sum = 0.0;
  int count = 0;
  for (int q = 0; q < rig.num_springs(); ++q) {
    if (rig.spring_kind()[q] != SpringKind::kStructure) continue;
    const double l = (x.row(rig.spring_a()[q]) - x.row(rig.spring_b()[q])).norm();
    sum += std::abs(l - blended[q]) / blended[q];
    ++count;
  }
  return sum / count;
}

struct RigCase {
  const char* rest;
  std::vector<const char*> targets;
  BoundaryMode mode;
};

std::string RigCaseName(const RigCase& c) {
  std::string text = c.rest;
  for (const char* target : c.targets) text += std::string(" + ") + target;
  return text;
}

// Readable in ctest's output (gtest prints a parameter without PrintTo as raw bytes).
void PrintTo(const RigCase& c, std::ostream* os) { *os << RigCaseName(c); }

class ReproducesShapes : public ::testing::TestWithParam<RigCase> {
 protected:
  std::shared_ptr<const Rig> Build() const {
    std::vector<std::string> targets(GetParam().targets.begin(), GetParam().targets.end());
    auto rig = LoadRig(GetParam().rest, targets);
    EXPECT_EQ(rig->boundary_mode(), GetParam().mode);
    return rig;
  }
};

TEST_P(ReproducesShapes, AlphaZeroGivesTheRestShape) {
  auto rig = Build();
  Solver solver(rig);
  Points x;
  const SolveSummary s = solver.Solve({std::vector<double>(rig->num_targets(), 0.0)}, &x);
  ASSERT_TRUE(s.converged()) << s.message;
  EXPECT_LE(MaxDistance(x, rig->rest().vertices), kShapeTolerance * Diagonal(*rig));
}

TEST_P(ReproducesShapes, AWeightOfOneGivesThatTarget) {
  auto rig = Build();
  for (int t = 0; t < rig->num_targets(); ++t) {
    std::vector<double> w(rig->num_targets(), 0.0);
    w[t] = 1.0;
    SolveOptions options;
    Solver solver(rig, options);
    Points x;
    const SolveSummary s = solver.Solve({w}, &x);
    ASSERT_TRUE(s.converged()) << s.message;
    EXPECT_LE(s.residual, options.residual_tolerance);
    EXPECT_LE(MaxDistance(x, rig->target(t).vertices), kShapeTolerance * Diagonal(*rig))
        << "target " << rig->target(t).name;
  }
}

INSTANTIATE_TEST_SUITE_P(
    BundledRigs, ReproducesShapes,
    ::testing::Values(
        RigCase{"cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, BoundaryMode::kFixedVertices},
        RigCase{"cylinder/cylinder.obj",
                {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-4.obj"},
                BoundaryMode::kFixedVertices},
        RigCase{"cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-2.obj"}, BoundaryMode::kAnchored},
        RigCase{"cube/cube.obj", {"cube/poses-1_cube-1.obj"}, BoundaryMode::kFixedVertices},
        RigCase{"cube/cube.obj", {"cube/poses-1_cube-4.obj", "cube/poses-2_cube-1.obj"},
                BoundaryMode::kAnchored}),
    // A name per case (mesh, target count, boundary), so that CTest lists and filters each one (without it
    // every case showed as ".../40-byte" and ran under one name).
    [](const ::testing::TestParamInfo<RigCase>& rig) {
      const std::string rest = rig.param.rest;
      const std::string mesh = rest.substr(0, rest.find('/'));
      return mesh + "_" + std::to_string(rig.param.targets.size()) + "_targets_" +
             (rig.param.mode == BoundaryMode::kAnchored ? "anchored" : "fixed");
    });

TEST(Sweep, EndsExactlyOnTheTargetWithEveryFrameInEquilibrium) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  Solver solver(rig);
  const auto frames = SweepFrames({1.0}, 12);
  ASSERT_EQ(frames.size(), 12u);
  EXPECT_EQ(frames.front().weights[0], 0.0);
  EXPECT_EQ(frames.back().weights[0], 1.0);
  Points x, previous;
  double largest_jump = 0.0, largest_linear_jump = 0.0;
  for (size_t i = 0; i < frames.size(); ++i) {
    const SolveSummary s = solver.Solve(frames[i], &x);
    ASSERT_TRUE(s.converged()) << "frame " << i << ": " << s.message;
    EXPECT_LE(s.residual, solver.options().residual_tolerance) << "frame " << i;
    if (i > 0) {
      largest_jump = std::max(largest_jump, MaxDistance(x, previous));
      largest_linear_jump = std::max(
          largest_linear_jump,
          MaxDistance(LinearBlend(*rig, frames[i].weights), LinearBlend(*rig, frames[i - 1].weights)));
    }
    previous = x;
  }
  EXPECT_LE(MaxDistance(x, rig->target(0).vertices), kShapeTolerance * Diagonal(*rig));
  // Smooth: no frame jumps much further than the linear blendshape moves per frame.
  EXPECT_LE(largest_jump, 3.0 * largest_linear_jump);
}

// Solves `frames` in order with one solver; returns each frame's positions and the total Newton iterations.
TEST(Blend, KeepsEdgeLengthsFarCloserToTheBlendedRestLengthsThanLinearBlending) {
  // A bending target: rotating parts shrink under linear blending (paper Fig. 1); springs do not.
  for (const char* target : {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-3.obj"}) {
    auto rig = LoadRig("cylinder/cylinder.obj", {target});
    Solver solver(rig);
    Points x;
    const SolveSummary s = solver.Solve({{0.5}}, &x);
    ASSERT_TRUE(s.converged()) << s.message;
    const double physical = EdgeLengthError(*rig, x, {0.5});
    const double linear = EdgeLengthError(*rig, LinearBlend(*rig, {0.5}), {0.5});
    RecordProperty(std::string("edge_error_ratio_") + target, std::to_string(linear / physical));
    EXPECT_GT(linear, 5.0 * physical) << target << ": linear " << linear << ", springs " << physical;
  }
}

// Every sparse Cholesky backend reaches the same equilibrium; MUMPS factors in single precision, and the
// answer still passes the convergence test in double.
TEST(Blend, EveryBackendAgrees) {
  auto cholmod = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-3.obj"}, testing::NoPathsRigOptions());
  Points a;
  ASSERT_TRUE(Solver(cholmod).Solve({{0.6}}, &a).converged());
  for (const LinearSolverType type : {LinearSolverType::kEigenSimplicial, LinearSolverType::kMumpsSingle}) {
    RigOptions options = testing::NoPathsRigOptions();
    options.linear_solver = type;
    auto other = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-3.obj"}, options);
    Points b;
    const SolveSummary summary = Solver(other).Solve({{0.6}}, &b);
    ASSERT_TRUE(summary.converged()) << ToString(type) << ": " << summary.message;
    EXPECT_LE(summary.residual, SolveOptions{}.residual_tolerance) << ToString(type);
    EXPECT_LE(MaxDistance(a, b), kShapeTolerance * Diagonal(*cholmod)) << ToString(type);
  }
}

TEST(Blend, ProjectedNewtonReachesTheSameEquilibrium) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  SolveOptions projected;
  projected.hessian = HessianMode::kProjected;
  projected.max_iterations = 1000;  // projected Newton converges only linearly
  Points a, b;
  const SolveSummary with_true = Solver(rig).Solve({{0.5}}, &a);
  const SolveSummary without = Solver(rig, projected).Solve({{0.5}}, &b);
  ASSERT_TRUE(with_true.converged()) << with_true.message;
  ASSERT_TRUE(without.converged()) << without.message;
  EXPECT_EQ(without.projected_factorizations, without.factorizations);
  EXPECT_LE(MaxDistance(a, b), kShapeTolerance * Diagonal(*rig));
}

// SolveOptions::certify_minimum. One surface vertex of the cylinder is left free and every other vertex pinned:
// its spring neighbours at an equal share of their rest lengths, two along +z and -z and the others evenly spread
// on a circle around it in the xy-plane, so its start is in balance (0 Newton iterations). Compressed to half their
// length, the circle's springs make z a direction of negative curvature (a compressed spring's transverse
// stiffness is negative) that the z springs do not outweigh: the buckling saddle, though the projected Hessian
// (curvature clamped at zero) is positive definite there, so only the true Hessian tells. Stretched to twice their
// length, a strict minimum. Converged frames of a rig are minima.
TEST(Blend, TheCertificateTellsAMinimumFromASaddle) {
  RigOptions options;
  options.interior = false;
  options.shell = false;
  options.anchor = false;
  options.static_tolerance = -1.0;
  options.target_paths = false;
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, options);
  const int free_vertex = 210;
  const Points& rest = rig->rest().vertices;
  std::vector<int> neighbours;
  std::vector<double> lengths;
  for (int k = rig->vertex_spring_offsets()[free_vertex]; k < rig->vertex_spring_offsets()[free_vertex + 1]; ++k) {
    const int q = rig->vertex_springs()[k];
    neighbours.push_back(rig->spring_a()[q] == free_vertex ? rig->spring_b()[q] : rig->spring_a()[q]);
    lengths.push_back(rig->rest_lengths()[q]);
  }
  ASSERT_GE(neighbours.size(), 4u);
  const auto frame_at = [&](double stretch) {
    Frame frame;
    frame.weights = {0.0};
    for (int v = 0; v < rig->num_vertices(); ++v) {
      if (v == free_vertex) continue;
      Eigen::Vector3d at = rest.row(v).transpose();
      const auto it = std::find(neighbours.begin(), neighbours.end(), v);
      if (it != neighbours.end()) {
        const size_t j = static_cast<size_t>(it - neighbours.begin());
        Eigen::Vector3d direction = Eigen::Vector3d::UnitZ() * (j == 0 ? 1.0 : -1.0);
        if (j >= 2) {
          const double angle = 2.0 * M_PI * static_cast<double>(j - 2) / static_cast<double>(neighbours.size() - 2);
          direction = Eigen::Vector3d(std::cos(angle), std::sin(angle), 0.0);
        }
        at = rest.row(free_vertex).transpose() + stretch * lengths[j] * direction;
      }
      frame.pins.push_back({v, at});
    }
    return frame;
  };
  SolveOptions certify;
  certify.certify_minimum = true;
  certify.use_target_paths = false;
  Solver solver(rig, certify);
  Points x;
  const SolveSummary saddle = solver.Solve(frame_at(0.5), &x);
  ASSERT_TRUE(saddle.converged()) << saddle.message;
  EXPECT_EQ(saddle.newton_iterations, 0);
  EXPECT_EQ(saddle.minimum, MinimumCheck::kNotMinimum);
  const SolveSummary stretched = solver.Solve(frame_at(2.0), &x);
  ASSERT_TRUE(stretched.converged()) << stretched.message;
  EXPECT_EQ(stretched.newton_iterations, 0);
  EXPECT_EQ(stretched.minimum, MinimumCheck::kMinimum);
  // Real frames of a rig (its own options, paths and all), and the default: not checked.
  auto full = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  Solver certified(full, certify);
  for (double w : {0.3, 0.7, 1.0}) {
    const SolveSummary s = certified.Solve({{w}}, &x);
    ASSERT_TRUE(s.converged()) << s.message;
    EXPECT_EQ(s.minimum, MinimumCheck::kMinimum) << w;
    EXPECT_GT(s.certify_ms, 0.0);
  }
  EXPECT_EQ(Solver(full).Solve({{0.7}}, &x).minimum, MinimumCheck::kNotChecked);
}

TEST(Blend, FixedVerticesMoveWithTheLinearBlend) {
  RigOptions options;
  options.fixed_vertices = {0, 1, 2, 200, 419};
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-3.obj"}, options);
  Points x;
  ASSERT_TRUE(Solver(rig).Solve({{0.4}}, &x).converged());
  const Points linear = LinearBlend(*rig, {0.4});
  for (int v : options.fixed_vertices) EXPECT_EQ(x.row(v), linear.row(v)) << "vertex " << v;
}

TEST(Blend, WeightsOutsideTheUnitIntervalStillSolve) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  std::vector<double> blended;
  BlendRestLengths(*rig, {-3.0}, &blended);
  for (double r : blended) ASSERT_GT(r, 0.0);
  for (double w : {-0.3, 1.3}) {
    Solver solver(rig);
    Points x;
    const SolveSummary s = solver.Solve({{w}}, &x);
    EXPECT_TRUE(s.converged()) << "w = " << w << ": " << s.message;
    EXPECT_TRUE(x.allFinite());
  }
}

TEST(Blend, LinearOptionGivesThePlainLinearBlendshape) {
  auto rig = LoadRig("cylinder/cylinder.obj",
                     {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-2.obj"});
  SolveOptions options;
  options.linear = true;
  Points x;
  const SolveSummary s = Solver(rig, options).Solve({{0.25, 0.5}}, &x);
  EXPECT_EQ(s.termination, Termination::kLinear);
  const Points expected = 0.25 * rig->rest().vertices + 0.25 * rig->target(0).vertices +
                          0.5 * rig->target(1).vertices;
  EXPECT_LE(MaxDistance(x, expected), 1e-12);
}

TEST(Blend, PartiallyFixedRigSolves) {
  RigOptions options = testing::NoPathsRigOptions();
  options.fixed_vertices = {10};
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, options);
  ASSERT_EQ(rig->boundary_mode(), BoundaryMode::kFixedVertices);  // the static end already fixes it
  options.static_tolerance = -1.0;
  auto partial = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, options);
  ASSERT_EQ(partial->boundary_mode(), BoundaryMode::kPartiallyFixed);
  Points x;
  const SolveSummary s = Solver(partial).Solve({{1.0}}, &x);
  ASSERT_TRUE(s.converged()) << s.message;
  EXPECT_EQ(x.row(10), partial->target(0).vertices.row(10));
}

TEST(Blend, IterationCapIsReportedNotHidden) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  SolveOptions options;
  options.max_iterations = 1;
  options.residual_tolerance = 1e-14;
  options.use_target_paths = false;  // from the linear blend: far enough that one iteration cannot do
  Points x;
  const SolveSummary s = Solver(rig, options).Solve({{0.5}}, &x);
  EXPECT_EQ(s.termination, Termination::kMaxIterations);
  EXPECT_FALSE(s.converged());
  EXPECT_EQ(s.newton_iterations, 1);
  EXPECT_GT(s.residual, options.residual_tolerance);
  EXPECT_THAT(s.message, HasSubstr("1 Newton iterations"));
}

// A stop check ends the frame at the next iteration (a server's cancelled request or overtaken slider frame);
// the same Solver then solves the next frame to the end.
TEST(Blend, AStopCheckEndsTheFrameAtTheNextIteration) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  SolveOptions options;
  options.use_target_paths = false;  // from the linear blend: several iterations to go
  Solver solver(rig, options);
  Points x;
  int asked = 0;
  const SolveSummary stopped = solver.Solve({{0.5}}, &x, [&] { return ++asked > 1; });
  EXPECT_EQ(stopped.termination, Termination::kCancelled);
  EXPECT_STREQ(ToString(stopped.termination), "cancelled");
  EXPECT_FALSE(stopped.converged());
  EXPECT_EQ(stopped.newton_iterations, 1);
  EXPECT_EQ(asked, 2);
  const SolveSummary full = solver.Solve({{0.5}}, &x, [] { return false; });
  EXPECT_TRUE(full.converged()) << full.message;
  EXPECT_GT(full.newton_iterations, 1);
}

TEST(Blend, SolversOnTwoThreadsShareOneRig) {
  auto rig = LoadRig("cylinder/cylinder.obj",
                     {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-2.obj"});
  Points reference;
  ASSERT_TRUE(Solver(rig).Solve({{0.3, 0.4}}, &reference).converged());
  Points results[2];
  bool converged[2] = {false, false};
  std::thread threads[2];
  for (int i = 0; i < 2; ++i) {
    threads[i] = std::thread([&, i] {
      Solver solver(rig);
      converged[i] = solver.Solve({{0.3, 0.4}}, &results[i]).converged();
    });
  }
  for (auto& t : threads) t.join();
  for (int i = 0; i < 2; ++i) {
    EXPECT_TRUE(converged[i]);
    EXPECT_LE(MaxDistance(results[i], reference), 1e-9 * Diagonal(*rig));
  }
}

// Solver::bytes (what a server's memory budget counts for a session) covers what the solver really holds after
// its frames, measured as glibc's heap in use (the sanitizers replace the allocator, so they measure nothing),
// without counting it several times over.
TEST(Blend, SolverBytesCoverWhatASolverHoldsAfterAFrame) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "the sanitizers' allocator is not glibc's";
#else
  RigOptions options;
  options.target_paths = false;
  for (const auto& [rest, target] :
       std::vector<std::pair<std::string, std::string>>{{"cylinder/cylinder.obj", "cylinder/poses-2_cylinder-1.obj"},
                                                        {"cube/cube.obj", "cube/poses-1_cube-1.obj"}}) {
    const auto rig = LoadRig(rest, {target}, options);
    for (const SolveMethod method : {SolveMethod::kNewton, SolveMethod::kNewtonLaplacian, SolveMethod::kLbfgs}) {
      SolveOptions solve;
      solve.method = method;
      malloc_trim(0);
      const auto heap = [] {
        const struct mallinfo2 m = mallinfo2();
        return static_cast<std::int64_t>(m.uordblks + m.hblkhd);
      };
      const std::int64_t before = heap();
      Solver solver(rig, solve);
      const std::int64_t counted = solver.bytes();
      Points x;
      Frame pinned{{0.7}};
      pinned.pins.push_back({0, rig->rest().vertices.row(0).transpose() + Eigen::Vector3d(0.01, 0, 0)});
      for (const Frame& frame : {Frame{{0.7}}, pinned}) EXPECT_TRUE(solver.Solve(frame, &x).converged());
      const std::int64_t held = heap() - before;
      EXPECT_GE(counted, held) << rest << " " << ToString(method);
      // L-BFGS factors only when it falls back to Newton; it is counted as if it did.
      if (method != SolveMethod::kLbfgs) {
        EXPECT_LE(counted, 3 * held) << rest << " " << ToString(method);
      }
    }
  }
#endif
}

TEST(ValidateWeights, RefusesTheWrongCountNamingTheTargets) {
  auto rig = LoadRig("cylinder/cylinder.obj",
                     {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-2.obj"});
  Solver solver(rig);
  Points x;
  const Error e = CatchError([&] { solver.Solve({{0.5}}, &x); });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("weights has 1 entries but the rig has 2 targets"));
  EXPECT_THAT(e.what(), HasSubstr("poses-2_cylinder-2"));
}

TEST(ValidateWeights, RefusesNonFiniteWeightsNamingTheEntry) {
  auto rig = LoadRig("cylinder/cylinder.obj",
                     {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-2.obj"});
  Solver solver(rig);
  Points x;
  const Error e = CatchError([&] { solver.Solve({{0.5, std::nan("")}}, &x); });
  EXPECT_THAT(e.what(), HasSubstr("weights[1]"));
  EXPECT_THAT(e.what(), HasSubstr("poses-2_cylinder-2"));
  // The refusal changed nothing: the next good frame solves as if it had never come.
  Points y, z;
  ASSERT_TRUE(solver.Solve({{0.2, 0.1}}, &y).converged());
  ASSERT_TRUE(Solver(rig).Solve({{0.2, 0.1}}, &z).converged());
  EXPECT_LE(MaxDistance(y, z), 1e-12);
}

TEST(SolveOptions, RefusesValuesOutOfRange) {
  SolveOptions options;
  options.max_iterations = 0;
  EXPECT_THAT(CatchError([&] { options.Validate(); }).what(), HasSubstr("max_iterations"));
  options = {};
  options.residual_tolerance = -1;
  EXPECT_THAT(CatchError([&] { options.Validate(); }).what(), HasSubstr("residual_tolerance"));
}

TEST(SweepFrames, RefusesZeroSteps) {
  EXPECT_THAT(CatchError([] { SweepFrames({1.0}, 0); }).what(), HasSubstr("at least 1 step"));
}

}  // namespace
}  // namespace springblend
