// The solves along one target's path (path_sweep.h): samples by continuation, their exact tangents, and the
// midpoint checks, finished where they are out of balance only when they can be.
#include "path_sweep.h"

#include <algorithm>
#include <limits>

#include "local_finish.h"
#include "path_internals.h"
#include "rig_internals.h"
#include "rigid.h"

namespace springblend::internal {

namespace {

constexpr int kMaxHalvings = 3;
// A midpoint check first takes one Newton step in the span of the path's samples and tangents around it (as a
// path frame does) and is then finished where it is out of balance only (local_finish.h), at the samples'
// tolerances; where that gives up (more than kCheckSeedShare of the vertices still out of balance after the
// step, or a region beyond kCheckLocalShare of them), the capped full Newton goes on from there.
constexpr double kCheckSeedShare = 0.05;
constexpr double kCheckLocalShare = 0.15;
// A sample solved this far (of the diagonal) from its predicted start jumped to another branch.
constexpr double kJump = 1e-3;
// Exact tangents: the central difference step in alpha of the forces and of the correction's map (their
// truncation error is of order step^2), the conjugate gradients' relative residual, and their cap (a sample
// whose tangent does not converge within it gets none). A relative 1e-4 saved 7 % of a face's build but left
// the interpolant's error spread over the whole mesh, so frames' local finishes had more to solve.
constexpr double kTangentStep = 1e-4;
constexpr double kTangentAccuracy = 1e-6;
constexpr int kTangentCgIterations = 30;

// Samples are solved well below the path's tolerance, so that a midpoint check measures the interpolant's
// error rather than the solves'.
MinimizerOptions SampleOptions(double tolerance) {
  MinimizerOptions options;
  options.residual_tolerance = 1e-7;
  options.step_tolerance = 0.1 * tolerance;
  // A step over a fold starts near a saddle, where following the negative curvature the conjugate gradients
  // meet leaves it sooner. On the face's jawOpen path: 933 Newton and 5390 CG iterations against 1163 and 6648,
  // the build 69 s against 78 s (bench/paths_bench.cc). Every sample still passes the full convergence test.
  options.follow_negative_curvature = true;
  // The kept factorization is refactored sooner than a frame's (0.5): a sweep's samples move the Hessian
  // further from one to the next than a take's frames do, and a fresh factor also serves the sample's exact
  // tangent. On the face's jawOpen and eyeBlink_L: the build 12 % shorter (Newton's conjugate gradients 3299 ->
  // 1872, factorizations 98 -> 223).
  options.refactor_cost_ratio = 0.2;
  return options;
}

}  // namespace

PathSolver::PathSolver(const Rig& rig, int target, double tolerance, const std::function<bool()>* stop)
    : rig_(rig),
      target_(target),
      stop_(stop),
      sample_options_(SampleOptions(tolerance)),
      springs_(TopologyOf(rig)),
      linear_(rig.internals().pattern->matrix, *rig.internals().cholesky, rig.options().linear_solver),
      minimizer_(Minimizer::Create(sample_options_)),
      held_(3 * static_cast<size_t>(rig.num_vertices()), 0) {
  springs_.set_length_scale(rig.summary().mean_rest_length);
}

std::vector<double> PathSolver::Weights(double alpha) const {
  std::vector<double> weights(rig_.num_targets(), 0.0);
  weights[target_] = alpha;
  return weights;
}

PathSolver::Setup PathSolver::SetUp(double alpha) {
  Setup setup;
  setup.weights = Weights(alpha);
  const std::vector<double> shape_weights = rig_.ShapeWeights(setup.weights);
  setup.linear = LinearBlendShapes(rig_, shape_weights);
  std::vector<double> rest_lengths;
  BlendRestLengths(rig_, shape_weights, &rest_lengths);
  springs_.SetRestLengths(std::move(rest_lengths), rig_.spring_kind(), KindStiffness(rig_.options()),
                          StiffnessFloor(rig_));
  setup.conditions = ConditionsOf(rig_, shape_weights, setup.linear, {});
  return setup;
}

// The sculpted shape of a knot (alpha 0, an in-between's weight, 1): a zero correction when it is in
// balance (an unmasked shape: zero energy), else the equilibrium solved from it.
Sample PathSolver::End(double alpha) {
  const Setup setup = SetUp(alpha);
  const Points& linear = setup.linear;
  Eigen::VectorXd x(3 * linear.rows());
  for (Eigen::Index v = 0; v < linear.rows(); ++v) x.segment<3>(3 * v) = linear.row(v).transpose();
  if (!HoldConditions(rig_, setup.conditions, &x, &held_) ||
      springs_.Evaluate(x, held_, Curvature{}, false) > SampleOptions(1.0).residual_tolerance) {
    const Eigen::MatrixXd zero = Eigen::MatrixXd::Zero(rig_.num_vertices(), 3);
    return Solve(alpha, nullptr, &zero);
  }
  Sample sample{alpha, Eigen::MatrixXd::Zero(rig_.num_vertices(), 3), Eigen::MatrixXd(), 0.0, true};
  sample.tangent = Tangent(alpha, std::move(x));
  return sample;
}

// The exact tangent at a sample given by its correction (anchor's frame).
Eigen::MatrixXd PathSolver::TangentOf(double alpha, const Eigen::MatrixXd& correction) {
  const Setup setup = SetUp(alpha);
  Eigen::MatrixXd world = correction;
  if (setup.conditions.motion) world = world * setup.conditions.motion->rotation.toRotationMatrix().transpose();
  const int n = rig_.num_vertices();
  Eigen::VectorXd x(3 * n);
  for (int v = 0; v < n; ++v) x.segment<3>(3 * v) = (setup.linear.row(v) + world.row(v)).transpose();
  if (!HoldConditions(rig_, setup.conditions, &x, &held_)) return {};
  return Tangent(alpha, std::move(x));
}

// The exact tangent of a sample's correction, d correction / d alpha (anchor's frame), at the equilibrium x
// of alpha (held coordinates in place, held_ marking them, the springs' rest lengths those of alpha):
// differentiating F_f(y_f(alpha), y_h(alpha), alpha) = 0 gives H_ff y_f' = g, g the derivative of the free
// forces in alpha with the free coordinates held (the rest lengths and the held vertices moving; central
// differences), solved by conjugate gradients with the kept factorization as preconditioner; the
// correction's map (minus the linear blend, rotated into the anchor's frame, or aligned for a floating
// rig) is then differentiated along (y', 1). Empty where the sample has no smooth tangent: at or next to an
// in-between's weight (a kink), or where the Hessian is not positive definite (a fold, a saddle).
Eigen::MatrixXd PathSolver::Tangent(double alpha, Eigen::VectorXd x) {
  if (stop_ != nullptr && *stop_ && (*stop_)()) ThrowCancelled();
  const double e = kTangentStep;
  for (const auto& knot : rig_.internals().controls.targets[target_]) {
    if (knot.weight < 1.0 && std::abs(alpha - knot.weight) <= 2 * e) return {};
  }
  const int n = rig_.num_vertices();
  Eigen::VectorXd g, velocity = Eigen::VectorXd::Zero(3 * n);
  for (const double side : {1.0, -1.0}) {
    const Setup moved = SetUp(alpha + side * e);
    Eigen::VectorXd y = x;
    for (const auto& [v, p] : moved.conditions.held) y.segment<3>(3 * v) = p;
    springs_.Evaluate(y, held_, Curvature{}, false);
    if (side > 0) {
      g = springs_.force();
    } else {
      g -= springs_.force();
    }
    velocity += side * (y - x);
  }
  g /= 2 * e;
  velocity /= 2 * e;  // nonzero on the held coordinates only
  const Setup here = SetUp(alpha);
  // The kept factorization (of a nearby sample) preconditions; where there is none, or it is too far off
  // for the conjugate gradients to converge within their cap, the Hessian at x is factorized (and kept for
  // the samples after it).
  const auto factorize = [&] {
    linear_.Select(held_);
    std::vector<double> values(springs_.topology().pattern->matrix.row_indices.size());
    const LadderResult ladder = FactorizeWithLadder(
        linear_, 0, 1.0 / rig_.summary().mean_rest_length,
        [&](double negative_scale, double shift) -> const std::vector<double>& {
          springs_.Assemble(x, held_, Curvature{negative_scale, false}, shift + here.conditions.diagonal_shift,
                            &values);
          return values;
        });
    return ladder.status == FactorStatus::kOk;
  };
  bool fresh = false;
  if (!linear_.has_factor() || !linear_.FactorCovers(held_)) {
    if (!factorize()) return {};
    fresh = true;
  }
  springs_.Evaluate(x, held_, Curvature{}, true);
  ConjugateGradientsOptions options;
  options.target_norm = kTangentAccuracy * g.norm();
  options.max_iterations = kTangentCgIterations;
  if (!cg_ || cg_->last_direction().size() != g.size()) cg_ = std::make_unique<ConjugateGradients>(g.size());
  Eigen::VectorXd z(g.size());
  const auto solve = [&] {
    return cg_->Solve(
        [&](const Eigen::VectorXd& v, Eigen::VectorXd* out) {
          springs_.HessianProduct(v, held_, here.conditions.diagonal_shift, out);
        },
        [&](const Eigen::VectorXd& r, Eigen::VectorXd* out) { linear_.Precondition(r, held_, out); }, g, options, &z,
        &tangent_cg_iterations);
  };
  ConjugateGradientsStatus status = solve();
  if (status == ConjugateGradientsStatus::kMaxIterations && !fresh) {
    if (stop_ != nullptr && *stop_ && (*stop_)()) ThrowCancelled();
    if (!factorize()) return {};
    springs_.Evaluate(x, held_, Curvature{}, true);
    status = solve();
  }
  // Negative curvature: the true Hessian is not positive definite at x (a saddle, a fold): no tangent.
  if (status != ConjugateGradientsStatus::kConverged || !z.allFinite()) return {};
  velocity += z;
  // The correction's map along (y', 1).
  Points ends[2];
  for (int i = 0; i < 2; ++i) {
    const double side = i == 0 ? 1.0 : -1.0;
    const Setup at = SetUp(alpha + side * e);
    Points solved(n, 3);
    for (int v = 0; v < n; ++v) solved.row(v) = (x.segment<3>(3 * v) + side * e * velocity.segment<3>(3 * v)).transpose();
    if (at.conditions.mode == BoundaryMode::kFloating) {
      AlignRigidly(at.linear.topRows(rig_.num_surface_vertices()), &solved);
    }
    ends[i] = solved - at.linear;
    if (at.conditions.motion) ends[i] = ends[i] * at.conditions.motion->rotation.toRotationMatrix();
  }
  SetUp(alpha);
  const Points tangent = (ends[0] - ends[1]) / (2 * e);
  if (!tangent.allFinite()) return {};
  return tangent;
}

// Solves alpha * target coming from `from` (the previous sample): where the continuation step is too long
// for Newton to converge, it is halved (up to three times) and the path followed through the midpoints,
// which are kept as samples too (in *out, ascending along the way).
void PathSolver::Refined(double from, double alpha, Continuation& continuation, std::vector<Sample>* out,
                         int depth) {
  Continuation before = continuation;
  Sample sample = Solve(alpha, &continuation, nullptr, depth < kMaxHalvings);
  if (std::isfinite(sample.energy) || depth >= kMaxHalvings) {
    out->push_back(std::move(sample));
    return;
  }
  continuation = std::move(before);
  const double middle = 0.5 * (from + alpha);
  Refined(from, middle, continuation, out, depth + 1);
  Refined(middle, alpha, continuation, out, depth + 1);
}

// Solves the target at alpha from the predictor's start, or from `correction` (anchor's frame) when given.
// A tentative solve that fails is not counted.
// max_iterations > 0 caps the Newton iterations (a midpoint check: an interpolant Newton does not finish
// from in a few iterations is not in its equilibrium's basin, whatever that equilibrium is).
Sample PathSolver::Solve(double alpha, Continuation* continuation, const Eigen::MatrixXd* correction, bool tentative,
                         int max_iterations, const TargetPath* around) {
  if (stop_ != nullptr && *stop_ && (*stop_)()) {
    ThrowCancelled();
  }
  const int n = rig_.num_vertices();
  const Setup setup = SetUp(alpha);
  const Points& linear = setup.linear;
  const FrameConditions& conditions = setup.conditions;
  // The start: the given correction, else the continuation's prediction with the least energy (where the
  // path bends sharply a higher order can overshoot).
  Eigen::VectorXd x;
  size_t predictions = 0;
  bool jumped = false;
  Points extrapolated, last;  // the highest-order prediction and the last sample (anchor's frame)
  const auto start_from = [&](const auto& c, Eigen::VectorXd* out) {
    Eigen::MatrixXd world = c;
    if (conditions.motion) world = world * conditions.motion->rotation.toRotationMatrix().transpose();
    out->resize(3 * n);
    for (int v = 0; v < n; ++v) out->segment<3>(3 * v) = (linear.row(v) + world.row(v)).transpose();
  };
  if (correction != nullptr) {
    start_from(*correction, &x);
  } else {
    double best = std::numeric_limits<double>::infinity();
    Eigen::VectorXd trial;
    const std::vector<Points> candidates = continuation->Candidates(alpha);
    predictions = candidates.size();
    if (predictions > 1) {
      extrapolated = candidates.back();
      last = candidates.front();
    }
    for (const Points& c : candidates) {
      start_from(c, &trial);
      HoldConditions(rig_, conditions, &trial, &held_);
      const double e = springs_.Energy(trial);
      if (!(e >= best)) {
        best = e;
        x.swap(trial);
      }
    }
    if (x.size() == 0) start_from(Eigen::MatrixXd::Zero(n, 3), &x);
  }
  MinimizerSummary summary;
  const bool held = HoldConditions(rig_, conditions, &x, &held_);
  if (held) {
    MinimizerProblem problem;
    problem.springs = &springs_;
    problem.linear = &linear_;
    problem.held = &held_;
    problem.diagonal_shift = conditions.diagonal_shift;
    problem.diagonal = rig_.summary().bounding_box_diagonal;
    problem.mean_rest_length = rig_.summary().mean_rest_length;
    problem.stop = stop_;
    MinimizerTiming timing;
    problem.timing = &timing;
    if (around == nullptr || !FinishLocally(alpha, conditions, *around, &x, &summary)) {
      if (max_iterations > 0) {
        MinimizerOptions capped = sample_options_;
        capped.max_iterations = max_iterations;
        minimizer_->SetOptions(capped);
      }
      minimizer_->Minimize(problem, &x, &summary);
      if (max_iterations > 0) minimizer_->SetOptions(sample_options_);
    }
  }
  if (summary.termination == MinimizerTermination::kCancelled) {
    ThrowCancelled();
  }
  const bool converged = summary.termination == MinimizerTermination::kConverged;
  newton_iterations += summary.iterations;
  if (!converged && tentative) {
    return {alpha, Eigen::MatrixXd(), Eigen::MatrixXd(), std::numeric_limits<double>::infinity(), false};
  }
  ++solves;
  Points solved(n, 3);
  for (int v = 0; v < n; ++v) solved.row(v) = x.segment<3>(3 * v).transpose();
  if (conditions.mode == BoundaryMode::kFloating) {
    AlignRigidly(linear.topRows(rig_.num_surface_vertices()), &solved);
  }
  const bool finite = solved.allFinite();
  if (!finite) solved = linear;  // a broken sample only costs its frames a worse start
  Points corrected = solved - linear;
  if (conditions.motion) corrected = corrected * conditions.motion->rotation.toRotationMatrix();  // R^T per row
  // A sample of the path (not a midpoint check) gets its exact tangent.
  Eigen::MatrixXd tangent;
  bool two_words = false;
  if (converged && finite && max_iterations == 0) {
    tangent = Tangent(alpha, x);
    two_words = NeedsTwoWords(alpha, corrected);
  }
  if (continuation != nullptr) {
    // A solve whose correction (aligned, for a floating rig: its gauge says nothing) landed far from the one
    // extrapolated along the branch, by more than half of what the step changed, went over a fold to
    // another branch: what came before it does not predict what comes after. (On a smooth branch the
    // extrapolation's error is of higher order in the step than the change.)
    if (predictions > 1) {
      const auto largest = [](const Points& d) { return std::sqrt(d.rowwise().squaredNorm().maxCoeff()); };
      const double missed = largest(corrected - extrapolated);
      jumped = missed > kJump * rig_.summary().bounding_box_diagonal && missed > 0.5 * largest(corrected - last);
    }
    if (jumped) continuation->Reset();
    if (converged && finite) continuation->Add(alpha, corrected, tangent);
  }
  return {alpha,
          std::move(corrected),
          std::move(tangent),
          converged && finite ? summary.energy : std::numeric_limits<double>::infinity(),
          converged && finite,
          jumped,
          false,
          two_words};
}

// A midpoint check's start x (the interpolant at alpha) finished as a path frame is: one Newton step in the
// span of the path's samples and tangents around alpha, then Newton where it is still out of balance only,
// to the samples' tolerances (the full convergence test on every free coordinate). x only moves to lower
// energy, so where this gives up (false) the full Newton goes on from x.
bool PathSolver::FinishLocally(double alpha, const FrameConditions& conditions, const TargetPath& around,
                               Eigen::VectorXd* x, MinimizerSummary* summary) {
  RefineInSpanOf(around, alpha, conditions.motion, sample_options_.residual_tolerance, &springs_, held_,
                 conditions.diagonal_shift, x);
  LocalFinishOptions finish;
  finish.residual_tolerance = sample_options_.residual_tolerance;
  finish.step_tolerance = sample_options_.step_tolerance;
  finish.max_share = kCheckLocalShare;
  finish.max_seed_share = kCheckSeedShare;
  finish.linear_solver = RegionLinearSolver(rig_.options().linear_solver);
  const LocalFinishResult result =
      LocalFinish(&springs_, held_, conditions.diagonal_shift, rig_.summary().bounding_box_diagonal,
                  rig_.summary().mean_rest_length, finish, stop_, x);
  if (stop_ != nullptr && *stop_ && (*stop_)()) ThrowCancelled();
  if (!result.converged) {
    newton_iterations += result.iterations;
    return false;
  }
  summary->iterations = result.iterations;
  ++local_checks;
  summary->termination = MinimizerTermination::kConverged;
  summary->residual = result.residual;
  summary->last_step = result.last_step;
  summary->energy = springs_.Energy(*x);
  return true;
}

// Whether a sample's correction (anchor's frame) needs two words (PathField): stored in one, the frame at
// its own alpha would start out of balance, its largest free force above the samples' tolerance and half
// again that of the correction itself.
bool PathSolver::NeedsTwoWords(double alpha, const Points& correction) {
  const Setup setup = SetUp(alpha);
  const auto force_at = [&](const Eigen::MatrixXd& c) {
    Eigen::MatrixXd world = c;
    if (setup.conditions.motion) world = world * setup.conditions.motion->rotation.toRotationMatrix().transpose();
    Eigen::VectorXd x(3 * world.rows());
    for (Eigen::Index v = 0; v < world.rows(); ++v) x.segment<3>(3 * v) = (setup.linear.row(v) + world.row(v)).transpose();
    HoldConditions(rig_, setup.conditions, &x, &held_);
    return springs_.Evaluate(x, held_, Curvature{}, false);
  };
  const double own = force_at(correction);
  const double stored = force_at(PathField(correction).Decode());
  return stored > std::max(sample_options_.residual_tolerance, 1.5 * own);
}

}  // namespace springblend::internal
