// Target paths (RigOptions::target_paths) and the frames they answer: every single-target frame, on sample or
// off, inside [0, 1], at an in-between's weight or extrapolated, converges and equals the same frame solved
// tightly from the same start within the certified bound; certified frames finish locally, on a part of the
// vertices; the ends and the in-betweens are reproduced exactly; the build is deterministic, persists
// (SavePrecomputed) and refuses bytes of another rig; a stop check ends a build within a second.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <sys/resource.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <thread>

#include "springblend/rig.h"
#include "springblend/solve.h"
#include "frame_conditions.h"
#include "local_finish.h"
#include "rig_internals.h"
#include "spring_system.h"
#include "target_paths.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CatchError;
using testing::DataPath;
using testing::MaxDistance;

// The bundled cylinder bending, with an in-between (a two-segment path), and twisting.
std::vector<TargetSpec> CylinderSpecs() {
  TargetSpec bend;
  bend.name = "bend";
  bend.mesh = LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"));
  bend.inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj"))});
  TargetSpec twist;
  twist.name = "twist";
  twist.mesh = LoadMesh(DataPath("cylinder/poses-1_cylinder-4.obj"));
  std::vector<TargetSpec> specs;
  specs.push_back(std::move(bend));
  specs.push_back(std::move(twist));
  return specs;
}

std::shared_ptr<const Rig> Cylinder(RigOptions options = {}) {
  return Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), CylinderSpecs(), options);
}

const std::shared_ptr<const Rig>& SharedCylinder() {
  static const std::shared_ptr<const Rig> rig = Cylinder();
  return rig;
}

SolveOptions Tight() {
  SolveOptions options;
  options.local_finish = false;
  options.residual_tolerance = 1e-12;
  options.step_tolerance = 1e-12;
  options.max_iterations = 400;
  return options;
}

TEST(TargetPaths, SummaryReportsEachTargetsPath) {
  const Rig& rig = *SharedCylinder();
  const RigSummary& s = rig.summary();
  ASSERT_EQ(s.paths.size(), 2u);
  EXPECT_EQ(s.paths[0].target, "bend");
  EXPECT_EQ(s.paths[1].target, "twist");
  int samples = 0, local_checks = 0;
  for (const auto& p : s.paths) {
    EXPECT_GE(p.samples, 2);
    EXPECT_LE(p.samples, rig.options().path_max_samples);
    EXPECT_GE(p.solves, p.samples - 3);  // the knots in balance cost no solve
    EXPECT_GE(p.max_error, 0.0);
    EXPECT_LE(p.max_error, rig.options().path_tolerance);
    EXPECT_LE(p.checks, p.solves);
    EXPECT_GE(p.local_checks, 0);
    EXPECT_LE(p.local_checks, p.checks);
    // The uncertified intervals' weights: ascending, apart (neighbours merged), within the path's reach, and
    // there exactly when some interval is uncertified.
    EXPECT_EQ(p.uncertified_ranges.empty(), p.uncertified == 0) << p.target;
    EXPECT_LE(static_cast<int>(p.uncertified_ranges.size()), p.uncertified) << p.target;
    double last = -1.0 - rig.options().path_extension;
    for (const auto& [from, to] : p.uncertified_ranges) {
      EXPECT_GT(from, last) << p.target;
      EXPECT_LT(from, to) << p.target;
      EXPECT_LE(to, 1.0 + rig.options().path_extension) << p.target;
      last = to;
    }
    std::cout << p.target << ": " << p.samples << " samples, " << p.checks << " midpoint checks (" << p.local_checks
              << " finished locally), " << p.uncertified << " intervals uncertified in " << p.uncertified_ranges.size()
              << " ranges\n";
    samples += p.samples;
    local_checks += p.local_checks;
  }
  // Midpoint checks start from the interpolant, most of them within the tolerance of their equilibrium: the span
  // step and a local finish settle some without a Newton solve of the whole mesh.
  EXPECT_GT(local_checks, 0);
  EXPECT_EQ(s.path_samples, samples);
  EXPECT_FALSE(s.paths_loaded);
  EXPECT_GT(s.path_bytes, 0);
  EXPECT_GT(s.rig_bytes, 0);
}

TEST(TargetPaths, EndsAndInbetweensAreReproducedExactly) {
  const auto& rig = SharedCylinder();
  Solver solver(rig);
  const Points rest = rig->rest().vertices;
  const Points inbetween = LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj")).vertices;
  const Points bend = LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj")).vertices;
  const double tolerance = 1e-6 * rig->summary().bounding_box_diagonal;
  const int surface = rig->num_surface_vertices();
  EXPECT_LE(MaxDistance(solver.Start({0.0, 0.0}).topRows(surface), rest), tolerance);
  EXPECT_LE(MaxDistance(solver.Start({0.5, 0.0}).topRows(surface), inbetween), tolerance);
  EXPECT_LE(MaxDistance(solver.Start({1.0, 0.0}).topRows(surface), bend), tolerance);
}

// Random alphas (in-between weights, the ends, extrapolated ones among them) of each target alone: the
// shipped solve converges and lands within the certified bound of the same frame solved to 1e-12.
TEST(TargetPaths, PathFramesEqualTightlySolvedFrames) {
  const auto& rig = SharedCylinder();
  Solver shipped(rig), tight(rig, Tight());
  std::mt19937 random(7);
  std::uniform_real_distribution<double> alpha(-0.25, 1.25);
  std::vector<double> alphas = {0.5, 1.0, -0.25, 1.25, 0.5 + 1e-7};
  for (int i = 0; i < 8; ++i) alphas.push_back(alpha(random));
  const double diagonal = rig->summary().bounding_box_diagonal;
  int local = 0, frames = 0;
  for (int t = 0; t < rig->num_targets(); ++t) {
    for (double a : alphas) {
      Frame frame;
      frame.weights.assign(rig->num_targets(), 0.0);
      frame.weights[t] = a;
      Points x, reference;
      const SolveSummary summary = shipped.Solve(frame, &x);
      ASSERT_TRUE(summary.converged()) << "target " << t << " alpha " << a << ": " << summary.message;
      EXPECT_LE(summary.residual, SolveOptions{}.residual_tolerance);
      const SolveSummary r = tight.Solve(frame, &reference);
      ASSERT_TRUE(r.converged()) << r.message;
      // The bound a converged frame is held to: the solve's own tolerances are about 1e-7 of the diagonal here.
      EXPECT_LE(MaxDistance(x, reference) / diagonal, 1e-6) << "target " << t << " alpha " << a;
      ++frames;
      if (summary.finish == Finish::kLocal) {
        ++local;
        EXPECT_LE(summary.solved_vertices, summary.free_vertices);
      } else {
        EXPECT_EQ(summary.finish, Finish::kFull);
        EXPECT_EQ(summary.solved_vertices, summary.free_vertices);
      }
    }
  }
  std::cout << local << " of " << frames << " frames finished locally\n";
}

// A target that moves a patch of the cylinder only (a bump pushed out near one vertex), every vertex free
// (held by the anchor), not only the patch.
std::shared_ptr<const Rig> Bump(RigOptions options = {}) {
  TriangleMesh rest = LoadMesh(DataPath("cylinder/cylinder.obj"));
  TriangleMesh bump = rest;
  bump.name = "bump";
  const double diagonal = (rest.vertices.colwise().maxCoeff() - rest.vertices.colwise().minCoeff()).norm();
  const Eigen::RowVector3d centre = rest.vertices.row(rest.vertices.rows() / 2);
  for (Eigen::Index v = 0; v < rest.vertices.rows(); ++v) {
    const double d = (rest.vertices.row(v) - centre).norm();
    if (d < 0.08 * diagonal) bump.vertices.row(v) += Eigen::RowVector3d(0.02 * diagonal * (1.0 - d / (0.08 * diagonal)), 0, 0);
  }
  std::vector<TriangleMesh> targets;
  targets.push_back(std::move(bump));
  options.static_tolerance = -1.0;
  return Rig::Build(std::move(rest), std::move(targets), options);
}

// The sweep solves a step every 1/path_intervals. Every step is kept while the cap allows (they were solved anyway, and
// denser samples give frames starts a local finish can use); under a tighter cap, on a smooth branch (the
// bump's) the path keeps only the steps its interpolant needs, checked against the ones it drops, and still
// certifies every interval. A tight cap holds even where the knots and the grid would ask for more (the
// cylinder's twist wrinkles: its path is not smooth).
TEST(TargetPaths, KeepsEveryStepTheCapAllowsAndOnlyWhatTheInterpolantNeedsBeyond) {
  const auto rig = Bump();
  const RigOptions& o = rig->options();
  const int steps = static_cast<int>(std::lround((1.0 + 2.0 * o.path_extension) * o.path_intervals));
  ASSERT_EQ(rig->summary().paths.size(), 1u);
  const auto& path = rig->summary().paths[0];
  EXPECT_GE(path.solves, steps - 3);
  EXPECT_GE(path.samples, steps + 1) << path.samples << " samples of " << steps << " steps";
  EXPECT_EQ(path.uncertified, 0);
  EXPECT_LE(path.max_error, rig->options().path_tolerance);
  RigOptions sparse;
  sparse.path_max_samples = steps / 2;
  const auto thin = Bump(sparse);
  const auto& kept = thin->summary().paths[0];
  EXPECT_LE(kept.samples, steps / 2);
  EXPECT_LT(kept.samples, path.samples);
  EXPECT_EQ(kept.uncertified, 0);
  EXPECT_LE(kept.max_error, thin->options().path_tolerance);
  RigOptions capped;
  capped.path_max_samples = 6;
  const auto cylinder = Cylinder(capped);
  for (const auto& p : cylinder->summary().paths) EXPECT_LE(p.samples, 6) << p.target;
  Points x;
  Solver solver(cylinder);
  const SolveSummary summary = solver.Solve(Frame{{0.37, 0.8}}, &x);
  EXPECT_TRUE(summary.converged()) << summary.message;
}

// The bump's frames are out of balance near the patch only, and finish there.
TEST(TargetPaths, ALocalFinishSolvesOnlyPartOfTheVertices) {
  const auto rig = Bump();
  const double diagonal = rig->summary().bounding_box_diagonal;
  Solver solver(rig), tight(rig, Tight());
  int partial = 0;
  for (double a : {0.13, 0.37, 0.61, 0.83, 1.17}) {
    Points x, reference;
    const SolveSummary summary = solver.Solve({{a}}, &x);
    ASSERT_TRUE(summary.converged()) << summary.message;
    ASSERT_TRUE(tight.Solve({{a}}, &reference).converged());
    EXPECT_LE(MaxDistance(x, reference) / diagonal, 1e-6) << "alpha " << a;
    if (summary.finish == Finish::kLocal && summary.solved_vertices < summary.free_vertices / 2) ++partial;
    std::cout << "alpha " << a << ": " << ToString(summary.finish) << ", " << summary.solved_vertices << " of "
              << summary.free_vertices << " vertices solved " << summary.local_finish_note << "\n";
  }
  EXPECT_GE(partial, 3);
}

// A frame's spring system and start (the interpolant, held vertices in place) as the solver sets them up.
struct FrameStart {
  explicit FrameStart(const Rig& rig, const std::vector<double>& weights)
      : springs(internal::TopologyOf(rig)), held(3 * static_cast<size_t>(rig.num_vertices()), 0) {
    const std::vector<double> shape_weights = rig.ShapeWeights(weights);
    const Points linear = internal::LinearBlendShapes(rig, shape_weights);
    std::vector<double> rest_lengths;
    internal::BlendRestLengths(rig, shape_weights, &rest_lengths);
    springs.set_length_scale(rig.summary().mean_rest_length);
    springs.SetRestLengths(std::move(rest_lengths), rig.spring_kind(), internal::KindStiffness(rig.options()),
                           internal::StiffnessFloor(rig));
    conditions = internal::ConditionsOf(rig, shape_weights, linear, {});
    x.resize(3 * linear.rows());
    for (Eigen::Index v = 0; v < linear.rows(); ++v) x.segment<3>(3 * v) = linear.row(v).transpose();
    internal::AddPathCorrections(rig.internals().paths, weights, conditions.motion, &x);
    EXPECT_TRUE(internal::HoldConditions(rig, conditions, &x, &held));
  }
  int Refine(const Rig& rig, const std::vector<double>& weights) {
    return internal::RefineInPathSpan(rig.internals().paths, weights, conditions.motion, 1e-6, &springs, held,
                                      conditions.diagonal_shift, &x);
  }
  internal::SpringSystem springs;
  std::vector<char> held;
  internal::FrameConditions conditions;
  Eigen::VectorXd x;
};

double Distance(const Eigen::VectorXd& x, const Points& to) {
  double largest = 0.0;
  for (Eigen::Index v = 0; v < to.rows(); ++v) largest = std::max(largest, (x.segment<3>(3 * v) - to.row(v).transpose()).norm());
  return largest;
}

// The bump with paths twice as dense as the default, certified to 1e-6 and reaching 0.25 beyond [0, 1]: frames
// start so close to their equilibria that a local finish tightened far below the samples' tolerance still solves a small region.
std::shared_ptr<const Rig> CloseStartBump() {
  RigOptions close;
  close.path_intervals = 32;
  close.path_tolerance = 1e-6;
  close.path_extension = 0.25;  // 1.17 on the path too
  return Bump(close);
}

// The region's Hessian is factored by the rig's backend (CHOLMOD's supernodal factorization by default): it
// finishes the same frames, from the same starts, at the same equilibrium as Eigen's simplicial Cholesky.
TEST(TargetPaths, ALocalFinishGivesTheSameEquilibriumWithEitherBackend) {
  const auto rig = CloseStartBump();
  const double diagonal = rig->summary().bounding_box_diagonal;
  int partial = 0;
  for (double a : {0.13, 0.37, 0.61, 0.83, 1.17}) {
    Eigen::VectorXd answers[2];
    internal::LocalFinishResult results[2];
    const LinearSolverType backends[2] = {LinearSolverType::kCholmodSupernodal, LinearSolverType::kEigenSimplicial};
    for (int b = 0; b < 2; ++b) {
      FrameStart start(*rig, {a});
      internal::LocalFinishOptions options;
      // Tighter than the path's samples, so that most frames have a region to solve.
      options.residual_tolerance = 1e-8;
      options.step_tolerance = 1e-10;
      options.linear_solver = backends[b];
      results[b] = internal::LocalFinish(&start.springs, start.held, start.conditions.diagonal_shift, diagonal,
                                         rig->summary().mean_rest_length, options, nullptr, &start.x);
      ASSERT_TRUE(results[b].converged) << "alpha " << a << " backend " << b << ": " << results[b].why;
      answers[b] = start.x;
    }
    EXPECT_EQ(results[0].vertices, results[1].vertices) << "alpha " << a;
    EXPECT_EQ(results[0].rounds, results[1].rounds) << "alpha " << a;
    EXPECT_LE(results[0].residual, 1e-8);
    std::cout << "alpha " << a << ": " << results[0].vertices << " of " << results[0].free_vertices
              << " vertices solved in " << results[0].rounds << " rounds\n";
    double largest = 0.0;
    for (Eigen::Index v = 0; v < answers[0].size() / 3; ++v) {
      largest = std::max(largest, (answers[0].segment<3>(3 * v) - answers[1].segment<3>(3 * v)).norm());
    }
    EXPECT_LE(largest / diagonal, 1e-8) << "alpha " << a;
    if (results[0].vertices > 0 && results[0].vertices < results[0].free_vertices) ++partial;
  }
  EXPECT_GE(partial, 2);  // the frames did need a region solved
}

// The region's Hessian is the rig's own pattern restricted to the region and assembled in place: with single
// coordinates of the most out-of-balance vertices held as well (a gauge, a pin's plane), the region's Newton
// still converges as Newton does (one to three iterations a round from a start this close), leaves every held
// coordinate where it was, and lands where the other backend's region solve lands.
TEST(TargetPaths, ALocalFinishHoldsSingleCoordinatesAndConvergesAsNewtonDoes) {
  const auto rig = CloseStartBump();
  const double diagonal = rig->summary().bounding_box_diagonal;
  int checked = 0;
  for (double a : {0.37, 0.83}) {
    Eigen::VectorXd answers[2];
    const LinearSolverType backends[2] = {LinearSolverType::kCholmodSupernodal, LinearSolverType::kEigenSimplicial};
    for (int b = 0; b < 2; ++b) {
      FrameStart start(*rig, {a});
      // Hold x of the five vertices pushed hardest, y of the next five.
      start.springs.Evaluate(start.x, start.held, internal::Curvature{}, false);
      const Eigen::VectorXd& force = start.springs.force();
      std::vector<int> order(static_cast<size_t>(rig->num_vertices()));
      for (size_t v = 0; v < order.size(); ++v) order[v] = static_cast<int>(v);
      const auto push = [&](int v) { return force.segment<3>(3 * v).norm(); };
      std::stable_sort(order.begin(), order.end(), [&](int p, int q) { return push(p) > push(q); });
      for (int k = 0; k < 10; ++k) start.held[3 * static_cast<size_t>(order[k]) + (k < 5 ? 0 : 1)] = 1;
      const Eigen::VectorXd before = start.x;
      internal::LocalFinishOptions options;
      options.residual_tolerance = 1e-9;
      options.step_tolerance = 1e-11;
      options.linear_solver = backends[b];
      const internal::LocalFinishResult result =
          internal::LocalFinish(&start.springs, start.held, start.conditions.diagonal_shift, diagonal,
                                rig->summary().mean_rest_length, options, nullptr, &start.x);
      ASSERT_TRUE(result.converged) << "alpha " << a << " backend " << b << ": " << result.why;
      ASSERT_GT(result.vertices, 0) << "alpha " << a;
      EXPECT_LE(result.iterations, 3 * result.rounds) << "alpha " << a << " backend " << b;
      for (size_t d = 0; d < start.held.size(); ++d) {
        if (start.held[d]) {
          ASSERT_EQ(start.x[static_cast<Eigen::Index>(d)], before[static_cast<Eigen::Index>(d)]) << "coordinate " << d;
        }
      }
      EXPECT_LE(start.springs.Evaluate(start.x, start.held, internal::Curvature{}, false), 1e-9);
      answers[b] = start.x;
    }
    EXPECT_LE((answers[0] - answers[1]).lpNorm<Eigen::Infinity>() / diagonal, 1e-8) << "alpha " << a;
    ++checked;
  }
  EXPECT_EQ(checked, 2);
}

// The span step on a path of 16 steps per unit (its interpolant starts frames out of balance): it lowers the
// energy, never moves a held coordinate, brings the start closer to the frame's tight equilibrium, is
// deterministic, and leaves mixes, frames without a path and starts already in balance alone.
// The cylinder with paths of 16 steps per unit certified to 1e-6 over [-0.25, 1.25], so that most of the frames
// below start near their tight equilibria (built once for the span step's tests).
const std::shared_ptr<const Rig>& SpanCylinder() {
  static const std::shared_ptr<const Rig> rig = [] {
    RigOptions options;
    options.path_intervals = 16;
    options.path_tolerance = 1e-6;
    options.path_extension = 0.25;
    return Cylinder(options);
  }();
  return rig;
}

TEST(TargetPaths, TheSpanStepBringsTheStartCloserToTheEquilibrium) {
  const auto& rig = SpanCylinder();
  const double diagonal = rig->summary().bounding_box_diagonal;
  Solver tight(rig, Tight());
  int refined = 0, near = 0;
  for (int t = 0; t < rig->num_targets(); ++t) {
    for (double a : {0.3, 0.62, 0.9, 1.1}) {
      std::vector<double> weights(rig->num_targets(), 0.0);
      weights[t] = a;
      Points reference;
      ASSERT_TRUE(tight.Solve(Frame{weights}, &reference).converged());
      const Points& all = tight.all_positions();
      FrameStart start(*rig, weights);
      const Eigen::VectorXd before = start.x;
      const double energy = start.springs.Energy(before);
      const double residual = start.springs.Evaluate(before, start.held, internal::Curvature{}, false);
      const int vectors = start.Refine(*rig, weights);
      const std::string where = "target " + std::to_string(t) + " alpha " + std::to_string(a);
      if (vectors == 0) {
        EXPECT_EQ(start.x, before) << where;
        continue;
      }
      ++refined;
      EXPECT_GT(residual, 1e-6) << where;
      EXPECT_LE(vectors, 8) << where;  // two samples and their tangents either side of the interval, at most
      EXPECT_LT(start.springs.Energy(start.x), energy) << where;
      for (size_t d = 0; d < start.held.size(); ++d) {
        if (start.held[d]) {
          ASSERT_EQ(start.x[static_cast<Eigen::Index>(d)], before[static_cast<Eigen::Index>(d)]) << where;
        }
      }
      // Where the start is near the tight equilibrium (on its branch: the twist wrinkles, and far from its
      // samples a frame's tight solve may settle elsewhere), the step brings it at least ten times closer, or
      // as close as the samples it combines are to their own equilibria: they are solved to a largest force of
      // 1e-7 (a sample taken from a midpoint check finished locally keeps its held vertices just below that),
      // a few 1e-8 of the diagonal on this rig.
      const double from = Distance(before, all) / diagonal, to = Distance(start.x, all) / diagonal;
      if (from < 1e-4) {
        ++near;
        EXPECT_LT(to, std::max(0.1 * from, 5e-8)) << where << ": " << from << " -> " << to << " of the diagonal";
      }
      std::cout << where << ": " << vectors << " vectors, " << from << " -> " << to << " of the diagonal\n";
      FrameStart again(*rig, weights);
      EXPECT_EQ(again.Refine(*rig, weights), vectors);
      EXPECT_EQ(again.x, start.x) << where;
    }
  }
  EXPECT_GE(refined, 6);
  EXPECT_GE(near, 5);
  // A mix moves two targets: its equilibrium is in neither path's span.
  FrameStart mix(*rig, {0.3, 0.6});
  const Eigen::VectorXd before = mix.x;
  EXPECT_FALSE(internal::HasPathSpan(rig->internals().paths, {0.3, 0.6}));
  EXPECT_TRUE(internal::HasPathSpan(rig->internals().paths, {0.3, 0.0}));
  EXPECT_EQ(mix.Refine(*rig, {0.3, 0.6}), 0);
  EXPECT_EQ(mix.x, before);
  // On a sample (the target itself) the start is in balance already.
  FrameStart full(*rig, {1.0, 0.0});
  EXPECT_EQ(full.Refine(*rig, {1.0, 0.0}), 0);
}

// With the local finish limited to 5 % of the mesh, it gives up on most of these paths' frames; the span
// step then starts them close enough for the second try to finish more of them locally, at the same answers.
TEST(TargetPaths, TheSpanStepLetsMoreFramesFinishLocally) {
  const auto& rig = SpanCylinder();
  const double diagonal = rig->summary().bounding_box_diagonal;
  SolveOptions with;
  with.local_finish_share = 0.05;
  SolveOptions without = with;
  without.path_span_step = false;
  Solver span(rig, with), plain(rig, without), tight(rig, Tight());
  int local_with = 0, local_without = 0, stepped = 0;
  for (int t = 0; t < rig->num_targets(); ++t) {
    for (double a : {0.15, 0.3, 0.45, 0.62, 0.77, 0.9, 1.1, -0.1}) {
      std::vector<double> weights(rig->num_targets(), 0.0);
      weights[t] = a;
      Points x, y, reference;
      const SolveSummary s = span.Solve(Frame{weights}, &x);
      const SolveSummary p = plain.Solve(Frame{weights}, &y);
      ASSERT_TRUE(s.converged() && p.converged()) << s.message << " / " << p.message;
      ASSERT_TRUE(tight.Solve(Frame{weights}, &reference).converged());
      EXPECT_LE(MaxDistance(x, reference) / diagonal, 1e-6) << "target " << t << " alpha " << a;
      EXPECT_EQ(p.span_vectors, 0);
      local_with += s.finish == Finish::kLocal ? 1 : 0;
      local_without += p.finish == Finish::kLocal ? 1 : 0;
      stepped += s.span_vectors > 0 ? 1 : 0;
    }
  }
  std::cout << "finished locally: " << local_with << " with the span step, " << local_without << " without; "
            << stepped << " frames stepped\n";
  EXPECT_GT(stepped, 0);
  EXPECT_GT(local_with, local_without);
}

TEST(TargetPaths, LocalFinishOffGivesTheSameEquilibrium) {
  const auto& rig = SharedCylinder();
  SolveOptions full;
  full.local_finish = false;
  Solver local(rig), whole(rig, full);
  for (double a : {0.29, 0.71, 1.1}) {
    Points x, y;
    ASSERT_TRUE(local.Solve({{0.0, a}}, &x).converged());
    const SolveSummary summary = whole.Solve({{0.0, a}}, &y);
    ASSERT_TRUE(summary.converged());
    EXPECT_EQ(summary.finish, Finish::kFull);
    EXPECT_LE(MaxDistance(x, y) / rig->summary().bounding_box_diagonal, 1e-6) << "alpha " << a;
  }
}

// Each sample of a path carries its exact tangent (one linear solve with the sample's own Hessian), and the
// interpolant takes it: at grid samples of the bend (every 1/16 is a sample), the slope of the frames' start in
// the weight equals the slope of tightly solved equilibria. A three-point tangent from samples 1/32 apart
// misses it by about 1e-3 of its size; the exact one is within the linear solve's accuracy.
TEST(TargetPaths, SamplesCarryExactTangents) {
  const auto& rig = SharedCylinder();
  Solver tight(rig, Tight());
  const double delta = 1e-4;
  for (double a : {0.25, 0.375, 0.75}) {
    const auto slope = [&](const std::function<Points(double)>& at) {
      return Points((at(a + delta) - at(a - delta)) / (2 * delta));
    };
    const Points start_slope = slope([&](double w) { return tight.Start({w, 0.0}); });
    const Points solved_slope = slope([&](double w) {
      Points x;
      const SolveSummary s = tight.Solve(Frame{{w, 0.0}}, &x);
      EXPECT_TRUE(s.converged()) << s.message;
      return Points(tight.all_positions());
    });
    const double size = std::sqrt(solved_slope.rowwise().squaredNorm().maxCoeff());
    ASSERT_GT(size, 0.0);
    EXPECT_LE(MaxDistance(start_slope, solved_slope) / size, 1e-5) << "alpha " << a;
  }
}

// Every stored sample starts the frame at its own weight in balance: its largest free force within the
// samples' tolerance (1e-7) and half again their own, a sample that one word of fixed point would put out of
// balance being kept in two (PathField). Frames at a sample's weight then take no Newton iteration.
TEST(TargetPaths, EveryStoredSampleStartsItsFrameInBalance) {
  const auto bump = Bump();
  for (const Rig* rig : {SharedCylinder().get(), bump.get()}) {
    const auto& paths = rig->internals().paths;
    int checked = 0;
    for (size_t t = 0; t < paths.size(); ++t) {
      const internal::TargetPath& path = paths[t];
      if (path.empty() || path.unconverged > 0) continue;
      for (int k = 0; k < path.samples(); ++k) {
        std::vector<double> weights(rig->num_targets(), 0.0);
        weights[t] = path.alphas[k];
        FrameStart start(*rig, weights);
        const double force = start.springs.Evaluate(start.x, start.held, internal::Curvature{}, false);
        EXPECT_LE(force, 1.5e-7) << "target " << t << ", sample " << k << " at alpha " << path.alphas[k] << " of "
                                 << path.corrections[k].words() << " word(s)";
        ++checked;
      }
    }
    EXPECT_GE(checked, rig->options().path_intervals);
  }
  // A frame at a sample's weight (not a knot).
  const auto& rig = SharedCylinder();
  const internal::TargetPath& bend = rig->internals().paths[0];
  const int k = bend.samples() / 3;
  ASSERT_NE(bend.alphas[k], 0.0);
  Solver solver(rig);
  Points x;
  const SolveSummary summary = solver.Solve(Frame{{bend.alphas[k], 0.0}}, &x);
  ASSERT_TRUE(summary.converged()) << summary.message;
  EXPECT_EQ(summary.newton_iterations, 0);
  EXPECT_EQ(summary.solved_vertices, 0);
}

// Paths saved by earlier versions still load: "SBPATH03" (float corrections and tangents) and "SBPATH02"
// (float corrections, no tangents: the interpolant then takes three-point tangents); frames converge to the
// same equilibria.
TEST(TargetPaths, PathsOfEarlierVersionsStillLoad) {
  const auto& rig = SharedCylinder();
  const std::string bytes = rig->SavePrecomputed();
  std::string why;
  const auto paths = internal::ParseTargetPaths(bytes, rig->num_targets(), rig->num_vertices(), &why);
  ASSERT_TRUE(paths.has_value()) << why;
  for (const bool v3 : {true, false}) {
    // The layout: magic, path count, vertex count, then per path its samples, max error, solves, Newton
    // iterations, unconverged samples, alphas, breaks, interval kinds and float corrections; version 3 then
    // per sample whether it has a tangent, and those tangents as floats.
    std::string old(v3 ? "SBPATH03" : "SBPATH02", 8);
    const auto put = [&](const auto& value) { old.append(reinterpret_cast<const char*>(&value), sizeof(value)); };
    const auto put_floats = [&](const internal::PathField& field) {
      const Eigen::MatrixXf f = field.Decode().cast<float>();
      old.append(reinterpret_cast<const char*>(f.data()), sizeof(float) * f.size());
    };
    put(static_cast<std::uint32_t>(paths->size()));
    put(static_cast<std::uint32_t>(rig->num_vertices()));
    int with_tangents = 0;
    for (const internal::TargetPath& p : *paths) {
      put(static_cast<std::uint32_t>(p.samples()));
      if (p.empty()) continue;
      put(p.max_error);
      put(static_cast<std::int32_t>(p.solves));
      put(static_cast<std::int32_t>(p.newton_iterations));
      put(static_cast<std::int32_t>(p.unconverged));
      for (double a : p.alphas) put(a);
      old.append(reinterpret_cast<const char*>(p.breaks.data()), p.breaks.size());
      old.append(reinterpret_cast<const char*>(p.certified.data()), p.certified.size());
      for (const internal::PathField& c : p.corrections) put_floats(c);
      for (const internal::PathField& t : p.tangents) with_tangents += t.empty() ? 0 : 1;
      if (!v3) continue;
      for (const internal::PathField& t : p.tangents) old.push_back(t.empty() ? 0 : 1);
      for (const internal::PathField& t : p.tangents) {
        if (!t.empty()) put_floats(t);
      }
    }
    EXPECT_GT(with_tangents, rig->summary().path_samples / 2);
    RigBuildControl control;
    control.precomputed = &old;
    const auto loaded = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), CylinderSpecs(), {}, control);
    EXPECT_TRUE(loaded->summary().paths_loaded) << (v3 ? "version 3" : "version 2");
    if (v3) {
      EXPECT_EQ(loaded->summary().path_samples, rig->summary().path_samples);
    } else {
      EXPECT_LT(loaded->summary().path_bytes, rig->summary().path_bytes);  // no tangents
    }
    Solver shipped(loaded), reference(rig, Tight());
    for (double w : {0.3, 0.9}) {
      Points x, y;
      const SolveSummary summary = shipped.Solve(Frame{{w, 0.0}}, &x);
      ASSERT_TRUE(summary.converged()) << summary.message;
      ASSERT_TRUE(reference.Solve(Frame{{w, 0.0}}, &y).converged());
      EXPECT_LE(MaxDistance(x, y) / rig->summary().bounding_box_diagonal, 1e-6) << "alpha " << w;
    }
  }
}

TEST(TargetPaths, BuildIsDeterministicAndPersists) {
  const auto& rig = SharedCylinder();
  const std::string bytes = rig->SavePrecomputed();
  EXPECT_TRUE(Cylinder()->SavePrecomputed() == bytes) << "two builds of one rig gave different paths";

  RigBuildControl control;
  control.precomputed = &bytes;
  const std::vector<TargetSpec> specs = CylinderSpecs();
  const auto loaded = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, control);
  EXPECT_TRUE(loaded->summary().paths_loaded);
  EXPECT_EQ(loaded->summary().path_samples, rig->summary().path_samples);
  EXPECT_TRUE(loaded->SavePrecomputed() == bytes);
  Solver a(rig), b(loaded);
  for (double w : {0.3, 0.9}) {
    Points x, y;
    a.Solve({{w, 0.2}}, &x);
    b.Solve({{w, 0.2}}, &y);
    EXPECT_TRUE(x == y) << "frames differ";  // byte-identical
  }

  // Bytes that are not this rig's paths are not used: solved again, with a note.
  const std::string truncated = bytes.substr(0, bytes.size() / 2);
  control.precomputed = &truncated;
  const auto rebuilt = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, control);
  EXPECT_FALSE(rebuilt->summary().paths_loaded);
  EXPECT_THAT(rebuilt->summary().notes, ::testing::Contains(HasSubstr("precomputed target paths were not used")));
  EXPECT_TRUE(rebuilt->SavePrecomputed() == bytes);
  // Another rig's (one target) are refused too.
  const auto other = testing::LoadRig("cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-4.obj"});
  const std::string foreign = other->SavePrecomputed();
  control.precomputed = &foreign;
  EXPECT_FALSE(Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, control)->summary().paths_loaded);
}

// Paths read from a file (a cache file's part, RigBuildControl::precomputed_file) stay there: the rig holds only
// their metadata, and its frames are the in-memory rig's to the bit.
TEST(TargetPaths, PathsLeftInAFileGiveTheSameFramesAndAreNotHeld) {
  const auto& rig = SharedCylinder();
  const std::string bytes = rig->SavePrecomputed();
  testing::TempDir dir;
  const std::string file = (dir.path() / "character.cache").string();
  const std::string before(37, 'h'), after(11, 't');  // the paths as one part of a larger file
  {
    std::ofstream out(file, std::ios::binary);
    out << before << bytes << after;
  }
  RigBuildControl control;
  control.precomputed_file =
      PrecomputedLocation{file, static_cast<std::int64_t>(before.size()), static_cast<std::int64_t>(bytes.size())};
  const std::vector<TargetSpec> specs = CylinderSpecs();
  const auto loaded = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, control);
  const RigSummary& s = loaded->summary();
  ASSERT_TRUE(s.paths_loaded) << ::testing::PrintToString(s.notes);
  EXPECT_EQ(s.path_samples, rig->summary().path_samples);
  EXPECT_EQ(rig->summary().path_file_bytes, 0);
  EXPECT_GT(s.path_file_bytes, rig->summary().path_bytes * 9 / 10) << "the samples' words are in the file";
  EXPECT_LT(s.path_bytes, rig->summary().path_bytes / 10) << "the rig holds only the paths' metadata";
  EXPECT_TRUE(loaded->SavePrecomputed() == bytes);

  Solver a(rig), b(loaded);
  for (const std::vector<double>& w : std::vector<std::vector<double>>{
           {0.3, 0.0}, {0.5, 0.0}, {0.9, 0.0}, {-0.2, 0.0}, {1.2, 0.0}, {0.0, 0.7}, {0.6, 0.4}}) {
    Points x, y;
    const SolveSummary sa = a.Solve(Frame{w}, &x);
    const SolveSummary sb = b.Solve(Frame{w}, &y);
    ASSERT_TRUE(sa.converged() && sb.converged()) << sa.message << " / " << sb.message;
    EXPECT_TRUE(x == y) << "frames differ at " << w[0] << ", " << w[1];  // byte-identical
    EXPECT_TRUE(a.Start(w) == b.Start(w)) << "previews differ";
  }

  // The whole file is not paths (without the offset and size); a missing file: solved again, with a note.
  RigBuildControl whole;
  whole.precomputed_file = PrecomputedLocation{file};
  const auto rebuilt = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, whole);
  EXPECT_FALSE(rebuilt->summary().paths_loaded);
  EXPECT_THAT(rebuilt->summary().notes, ::testing::Contains(HasSubstr("precomputed target paths were not used")));
  RigBuildControl missing;
  missing.precomputed_file = PrecomputedLocation{(dir.path() / "absent.cache").string()};
  // Solved again, and kept where the caller writes them (as the server's cache file): the same frames, read from
  // there.
  const std::string persisted = (dir.path() / "persisted.cache").string();
  int persist_calls = 0;
  missing.persist = [&](const PrecomputedWriter& writer) {
    ++persist_calls;
    std::string solved_bytes;
    int pieces = 0;
    EXPECT_TRUE(writer([&](std::string_view piece) {
      ++pieces;
      solved_bytes.append(piece);
      return true;
    }));
    EXPECT_TRUE(solved_bytes == bytes);
    EXPECT_GE(pieces, 1);
    std::ofstream(persisted, std::ios::binary) << before << solved_bytes;
    return std::optional<PrecomputedLocation>(PrecomputedLocation{persisted, static_cast<std::int64_t>(before.size())});
  };
  const auto solved = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, missing);
  EXPECT_FALSE(solved->summary().paths_loaded);
  EXPECT_THAT(solved->summary().notes, ::testing::Contains(HasSubstr("absent.cache")));
  EXPECT_EQ(persist_calls, 1);
  EXPECT_TRUE(solved->SavePrecomputed() == bytes);
  EXPECT_EQ(solved->summary().path_file_bytes, s.path_file_bytes);
  EXPECT_EQ(solved->summary().path_bytes, s.path_bytes);
  {
    Solver d(solved);
    Points x, y;
    ASSERT_TRUE(d.Solve(Frame{{0.9, 0.0}}, &x).converged());
    a.Solve(Frame{{0.9, 0.0}}, &y);
    EXPECT_TRUE(x == y) << "a frame from the persisted paths differs";
  }
  // A caller that could not keep them (nullopt): held in memory, as without the callback.
  RigBuildControl unkept;
  unkept.persist = [](const PrecomputedWriter&) { return std::optional<PrecomputedLocation>(); };
  const auto held = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, unkept);
  EXPECT_EQ(held->summary().path_file_bytes, 0);
  EXPECT_EQ(held->summary().path_bytes, rig->summary().path_bytes);

  // A file cut short in place after the rig opened it (what the cache never does): a frame that needs a lost
  // sample fails with an error naming the file, not with garbage.
  std::filesystem::resize_file(file, before.size() + 64);
  Solver c(loaded);
  Points z;
  const Error e = CatchError([&] { c.Solve(Frame{{0.9, 0.0}}, &z); });
  EXPECT_EQ(e.code(), ErrorCode::kInternal);
  EXPECT_THAT(e.what(), HasSubstr("character.cache"));
}

// A build with a spool directory (RigBuildControl::spool_directory) leaves each target's path in a file without a
// name as soon as it is solved: the rig holds only the paths' metadata from then on, leaves nothing in the
// directory, gives the same bytes and frames to the bit, and tells its bytes in pieces that stop when asked.
TEST(TargetPaths, ABuildSpoolsEachPathAsItIsSolved) {
  const auto& rig = SharedCylinder();
  const std::string bytes = rig->SavePrecomputed();
  const std::vector<TargetSpec> specs = CylinderSpecs();
  testing::TempDir dir;
  RigBuildControl control;
  control.spool_directory = dir.path().string();
  int paths_done = 0;
  control.progress = [&](const RigBuildProgress& p) {
    if (p.stage == "paths" && p.targets_done > 0) paths_done = p.targets_done;
  };
  const auto spooled = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, control);
  const RigSummary& s = spooled->summary();
  EXPECT_EQ(paths_done, 2);
  EXPECT_THAT(s.notes, ::testing::Not(::testing::Contains(HasSubstr("held in memory"))))
      << ::testing::PrintToString(s.notes);
  EXPECT_EQ(s.path_samples, rig->summary().path_samples);
  EXPECT_GT(s.path_file_bytes, rig->summary().path_bytes * 9 / 10) << "the samples' words are in the spool";
  EXPECT_LT(s.path_bytes, rig->summary().path_bytes / 10) << "the rig holds only the paths' metadata";
  EXPECT_TRUE(std::filesystem::is_empty(dir.path())) << "the spool has no name";
  EXPECT_TRUE(spooled->SavePrecomputed() == bytes);
  std::string told;
  int pieces = 0;
  EXPECT_TRUE(spooled->WritePrecomputed([&](std::string_view piece) {
    ++pieces;
    told.append(piece);
    return true;
  }));
  EXPECT_TRUE(told == bytes);
  EXPECT_FALSE(spooled->WritePrecomputed([](std::string_view) { return false; })) << "a writer that stops";
  Solver a(rig), b(spooled);
  for (const std::vector<double>& w :
       std::vector<std::vector<double>>{{0.3, 0.0}, {0.9, 0.0}, {-0.2, 0.0}, {1.2, 0.0}, {0.6, 0.4}}) {
    Points x, y;
    ASSERT_TRUE(a.Solve(Frame{w}, &x).converged());
    ASSERT_TRUE(b.Solve(Frame{w}, &y).converged());
    EXPECT_TRUE(x == y) << "frames differ at " << w[0] << ", " << w[1];
  }

  // Kept by the caller too: read from its file from then on, the spool let go.
  const std::string persisted = (dir.path() / "persisted.cache").string();
  control.persist = [&](const PrecomputedWriter& writer) {
    std::ofstream out(persisted, std::ios::binary);
    EXPECT_TRUE(writer([&](std::string_view piece) {
      return static_cast<bool>(out.write(piece.data(), static_cast<std::streamsize>(piece.size())));
    }));
    return std::optional<PrecomputedLocation>(PrecomputedLocation{persisted});
  };
  const auto kept = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, control);
  EXPECT_TRUE(kept->SavePrecomputed() == bytes);
  EXPECT_EQ(kept->summary().path_file_bytes, s.path_file_bytes);
  EXPECT_EQ(std::filesystem::file_size(persisted), bytes.size());

  // A directory where no spool can be made: held in memory, with a note naming it; the same bytes.
  RigBuildControl nowhere;
  nowhere.spool_directory = (dir.path() / "absent").string();
  const auto held = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), specs, {}, nowhere);
  EXPECT_THAT(held->summary().notes, ::testing::Contains(HasSubstr("absent")));
  EXPECT_EQ(held->summary().path_file_bytes, 0);
  EXPECT_TRUE(held->SavePrecomputed() == bytes);
}

// A spool that fills (here the process's file-size limit, as a full disk would) keeps the paths it could not take
// in memory, says so, and changes nothing else: the same bytes and frames, part read from the spool, part held.
TEST(TargetPaths, ASpoolThatFillsKeepsThePathsInMemory) {
  const auto& rig = SharedCylinder();
  const std::string bytes = rig->SavePrecomputed();
  testing::TempDir dir;
  RigBuildControl control;
  control.spool_directory = dir.path().string();
  rlimit before{};
  ASSERT_EQ(getrlimit(RLIMIT_FSIZE, &before), 0);
  const auto old_handler = std::signal(SIGXFSZ, SIG_IGN);  // a write past the limit then fails with EFBIG
  rlimit limited = before;
  limited.rlim_cur = 64 * 1024;  // a few of the cylinder's fields
  ASSERT_EQ(setrlimit(RLIMIT_FSIZE, &limited), 0);
  std::shared_ptr<const Rig> spooled;
  try {
    spooled = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), CylinderSpecs(), {}, control);
  } catch (...) {
    setrlimit(RLIMIT_FSIZE, &before);
    std::signal(SIGXFSZ, old_handler);
    throw;
  }
  ASSERT_EQ(setrlimit(RLIMIT_FSIZE, &before), 0);
  std::signal(SIGXFSZ, old_handler);
  const RigSummary& s = spooled->summary();
  EXPECT_THAT(s.notes, ::testing::Contains(HasSubstr("some target paths were held in memory")))
      << ::testing::PrintToString(s.notes);
  EXPECT_GT(s.path_file_bytes, 0) << "the fields before the limit are in the spool";
  EXPECT_LE(s.path_file_bytes, 64 * 1024);
  EXPECT_GT(s.path_bytes, rig->summary().path_bytes / 2) << "the rest are held";
  EXPECT_TRUE(spooled->SavePrecomputed() == bytes);
  Solver a(rig), b(spooled);
  for (const std::vector<double>& w : std::vector<std::vector<double>>{{0.4, 0.0}, {1.1, 0.0}, {0.0, 0.8}}) {
    Points x, y;
    ASSERT_TRUE(a.Solve(Frame{w}, &x).converged());
    ASSERT_TRUE(b.Solve(Frame{w}, &y).converged());
    EXPECT_TRUE(x == y) << "frames differ at " << w[0] << ", " << w[1];
  }
}

TEST(TargetPaths, AStopCheckEndsTheBuildWithinASecond) {
  std::atomic<bool> stop{false};
  std::atomic<bool> paths_started{false};
  RigBuildControl control;
  control.stop = [&] { return stop.load(); };
  control.progress = [&](const RigBuildProgress& p) {
    if (p.stage == "paths") paths_started = true;
  };
  std::vector<TargetSpec> specs(1);
  specs[0].name = "pose";
  specs[0].mesh = LoadMesh(DataPath("cube/poses-1_cube-4.obj"));  // its path takes seconds
  std::chrono::steady_clock::time_point stopped;
  std::thread stopper([&] {
    while (!paths_started) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    stopped = std::chrono::steady_clock::now();
    stop = true;
  });
  const Error error = CatchError([&] { Rig::Build(LoadMesh(DataPath("cube/cube.obj")), specs, {}, control); });
  const auto ended = std::chrono::steady_clock::now();
  stopper.join();
  EXPECT_EQ(error.code(), ErrorCode::kCancelled);
  EXPECT_LT(std::chrono::duration<double>(ended - stopped).count(), 1.0 * testing::kSlowdown);
}

// A mix frame starts on the ray from the linear blend through its targets' summed corrections, at the lowest
// energy the walk down from the full sum meets. Corrections made to overshoot (three times the sum) are
// walked back to a lower energy, on the ray, with held coordinates kept; a single-target frame's start is
// left as it is; the solve from the scaled start converges to a certified minimum, the same bits twice.
TEST(TargetPaths, AMixStartsAtTheLowestEnergyOnItsCorrectionsRay) {
  const auto& rig = SharedCylinder();
  const std::vector<double> weights = {0.6, 0.7};
  ASSERT_TRUE(internal::IsPathMix(rig->internals().paths, weights));
  FrameStart start(*rig, weights);
  const Points linear = internal::LinearBlendShapes(*rig, rig->ShapeWeights(weights));
  Eigen::VectorXd base(start.x.size());
  for (Eigen::Index d = 0; d < base.size(); ++d) {
    base[d] = start.held[static_cast<size_t>(d)] ? start.x[d] : linear(d / 3, d % 3);
  }
  const auto energy = [&](const Eigen::VectorXd& y) { return start.springs.Energy(y); };
  for (double overshoot : {1.0, 3.0}) {
    const Eigen::VectorXd given = base + overshoot * (start.x - base);
    Eigen::VectorXd x = given;
    const double s = internal::ScaleMixStart(rig->internals().paths, weights, base, energy, &x);
    const std::string where = "overshoot " + std::to_string(overshoot);
    ASSERT_GE(s, 0.0) << where;
    ASSERT_LE(s, 1.0) << where;
    EXPECT_LE(energy(x), energy(given)) << where;
    EXPECT_LE(energy(x), energy(base + 0.875 * (given - base)) + 1e-15) << where;  // no higher than the walk's first step
    EXPECT_LT((x - (base + s * (given - base))).lpNorm<Eigen::Infinity>(), 1e-12) << where;
    for (size_t d = 0; d < start.held.size(); ++d) {
      if (start.held[d]) {
        ASSERT_EQ(x[static_cast<Eigen::Index>(d)], given[static_cast<Eigen::Index>(d)]) << where;
      }
    }
    if (overshoot == 3.0) {
      EXPECT_LT(s, 0.75) << where;  // at least two steps back
      EXPECT_LT(energy(x), 0.5 * energy(given)) << where;
    }
    Eigen::VectorXd again = given;
    EXPECT_EQ(internal::ScaleMixStart(rig->internals().paths, weights, base, energy, &again), s);
    EXPECT_EQ(again, x);
  }
  // One target: its path's own start, untouched.
  FrameStart single(*rig, {0.6, 0.0});
  Eigen::VectorXd x = single.x;
  EXPECT_EQ(internal::ScaleMixStart(rig->internals().paths, {0.6, 0.0}, base, energy, &x), 1.0);
  EXPECT_EQ(x, single.x);
  EXPECT_FALSE(internal::IsPathMix(rig->internals().paths, {0.6, 0.0}));

  SolveOptions options;
  options.certify_minimum = true;
  Solver solver(rig, options);
  Points first, second;
  const SolveSummary summary = solver.Solve(Frame{weights}, &first);
  ASSERT_TRUE(summary.converged()) << summary.message;
  EXPECT_EQ(summary.minimum, MinimumCheck::kMinimum);
  EXPECT_GE(summary.mix_start_scale, 0.0);
  EXPECT_LE(summary.mix_start_scale, 1.0);
  Solver other(rig, options);
  other.Solve(Frame{{0.6, 0.0}}, &second);  // an earlier frame changes nothing
  const SolveSummary repeat = other.Solve(Frame{weights}, &second);
  EXPECT_EQ(repeat.mix_start_scale, summary.mix_start_scale);
  EXPECT_EQ(first, second);
}

// Where a path is not certified: the intervals whose check did not pass (0) and folds (3), neighbours merged;
// certified intervals (1) and the switch between branches (2) are not among them.
TEST(TargetPaths, UncertifiedRangesMergeNeighbouringIntervals) {
  internal::TargetPath path;
  path.alphas = {-0.25, 0.0, 0.5, 0.75, 1.0, 1.1, 1.25};
  path.certified = {0, 3, 1, 0, 2, 0};
  using Ranges = std::vector<std::pair<double, double>>;
  EXPECT_EQ(path.UncertifiedRanges(), (Ranges{{-0.25, 0.5}, {0.75, 1.0}, {1.1, 1.25}}));
  EXPECT_EQ(path.uncertified(), 4);
  path.certified = {1, 1, 2, 1, 1, 1};
  EXPECT_TRUE(path.UncertifiedRanges().empty());
  path.certified = {3, 3, 3, 3, 3, 3};
  EXPECT_EQ(path.UncertifiedRanges(), (Ranges{{-0.25, 1.25}}));
}

TEST(TargetPaths, OptionsOutOfRangeAreRefused) {
  RigOptions options;
  options.path_tolerance = 0.0;
  EXPECT_THAT(CatchError([&] { options.Validate(); }).what(), HasSubstr("path_tolerance"));
  options = {};
  options.path_max_samples = 2;
  EXPECT_THAT(CatchError([&] { options.Validate(); }).what(), HasSubstr("path_max_samples"));
  SolveOptions solve;
  solve.local_finish_share = 0.0;
  EXPECT_THAT(CatchError([&] { solve.Validate(); }).what(), HasSubstr("local_finish_share"));
}

}  // namespace
}  // namespace springblend
