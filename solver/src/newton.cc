#include "newton.h"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>

#include "laplacian.h"
#include "lbfgs.h"
#include "line_search.h"

namespace springblend::internal {

namespace {

constexpr double kNoProgress = 1e-15;  // a step this short (of the diagonal) changes nothing
constexpr double kMaxForcing = 0.1;    // the loosest relative accuracy of a linear solve

}  // namespace

std::unique_ptr<Minimizer> Minimizer::Create(const MinimizerOptions& options) {
  switch (options.type) {
    case MinimizerType::kInexactNewton: return std::make_unique<InexactNewton>(options);
    case MinimizerType::kLbfgs: return std::make_unique<Lbfgs>(options);
  }
  return std::make_unique<InexactNewton>(options);
}

bool InexactNewton::FactorizeAndSolve(const MinimizerProblem& problem, const Eigen::VectorXd& x, double forcing,
                                      MinimizerSummary* summary) {
  const auto factor_start = std::chrono::steady_clock::now();
  SpringSystem& springs = *problem.springs;
  LinearSystem& linear = *problem.linear;
  const std::vector<char>& held = *problem.held;
  linear.Select(held);
  size_t first = options_.hessian == HessianChoice::kTrueWithProjectedFallback ? 0 : kFirstProjectedRung;
  // A factorization kept as a preconditioner need not be the exact Hessian: start one rung below the one
  // that worked last time, so a known-indefinite true Hessian is not factored again and again.
  if (options_.reuse_factorization && rung_ > first) first = std::max(first, rung_ - 1);
  values_.resize(springs.topology().pattern->matrix.row_indices.size());
  const LadderResult ladder = FactorizeWithLadder(
      linear, first, 1.0 / problem.mean_rest_length,
      [&](double negative_scale, double shift) -> const std::vector<double>& {
        springs.Assemble(x, held, CurvatureAt(negative_scale), shift + problem.diagonal_shift, &values_);
        return values_;
      });
  summary->factorizations += ladder.factorizations;
  summary->projected_factorizations += ladder.projected;
  summary->shifted_factorizations += ladder.shifted;
  summary->factorize_ms += ElapsedMs(factor_start);
  problem.timing->factorize_ms += ElapsedMs(factor_start);
  if (ladder.status != FactorStatus::kOk) {
    summary->message = "the Hessian could not be factorized even with a diagonal shift";
    return false;
  }
  rung_ = ladder.rung;
  refactor_next_ = false;
  // The per-spring blocks are left as the ladder assembled them: the line search reassembles at the new
  // iterate before any matrix-free product reads them.
  const auto solve_start = std::chrono::steady_clock::now();
  if (options_.reuse_factorization) {
    // The factor is kept to precondition the next steps, which round it to single precision for the two-thread
    // solve: this step uses that solve too (the cat: 3.8 ms against 11.2 for the double one; the rounding is paid
    // once for both). Its relative residual, about 1e-6 to 1e-4, meets the forcing term but in the last steps,
    // where one refinement takes it to about the square. The product is with the factored matrix: the blocks
    // the ladder assembled last, and its shift.
    const double shift = ladder.shift + problem.diagonal_shift;
    linear.SolveTo(
        springs.force(), held, forcing,
        [&](const Eigen::VectorXd& v, Eigen::VectorXd* product) { springs.HessianProduct(v, held, shift, product); },
        &step_);
  } else {
    linear.Solve(springs.force(), held, &step_);
  }
  problem.timing->solve_ms += ElapsedMs(solve_start);
  if (!step_.allFinite()) {
    summary->message = "the Newton step is not finite";
    return false;
  }
  return true;
}

ConjugateGradientsStatus InexactNewton::ConjugateGradientStep(const MinimizerProblem& problem, double forcing,
                                                              MinimizerSummary* summary) {
  const auto start = std::chrono::steady_clock::now();
  SpringSystem& springs = *problem.springs;
  const std::vector<char>& held = *problem.held;
  const Eigen::VectorXd& force = springs.force();  // zero on held coordinates, and so stays every vector
  ConjugateGradientsOptions cg;
  cg.target_norm = forcing * force.norm();
  cg.floor = 0.1 * options_.residual_tolerance;  // no need to solve below the tolerance
  cg.max_iterations = options_.max_cg_iterations;
  if (!cg_ || cg_->last_direction().size() != force.size()) cg_ = std::make_unique<ConjugateGradients>(force.size());
  const bool laplacian = options_.preconditioner == Preconditioner::kLaplacian;
  const auto status = cg_->Solve(
      [&](const Eigen::VectorXd& v, Eigen::VectorXd* out) {
        springs.HessianProduct(v, held, problem.diagonal_shift, out);
      },
      [&](const Eigen::VectorXd& r, Eigen::VectorXd* z) {
        if (laplacian) {
          problem.laplacian->Apply(r, held, z);
        } else {
          problem.linear->Precondition(r, held, z);
        }
      },
      force, cg, &step_, &summary->cg_iterations);
  if (status == ConjugateGradientsStatus::kNegativeCurvature && options_.follow_negative_curvature) {
    const Eigen::VectorXd& d = cg_->last_direction();
    if (d.allFinite() && std::isfinite(d.dot(d))) {
      negative_direction_ = d;
      has_negative_direction_ = true;
    }
  }
  problem.timing->solve_ms += ElapsedMs(start);
  return status;
}

bool InexactNewton::LaplacianDirection(const MinimizerProblem& problem, const Eigen::VectorXd& x, double forcing,
                                       MinimizerSummary* summary) {
  SpringSystem& springs = *problem.springs;
  const std::vector<char>& held = *problem.held;
  const auto usable = [&](ConjugateGradientsStatus status) {
    if (status == ConjugateGradientsStatus::kNegativeCurvature || !step_.allFinite()) return false;
    return status == ConjugateGradientsStatus::kConverged || springs.force().dot(step_) > 0.0;  // truncated
  };
  if (options_.hessian != HessianChoice::kProjected && usable(ConjugateGradientStep(problem, forcing, summary))) {
    return true;
  }
  if (options_.hessian == HessianChoice::kAbsolute) return false;
  const auto start = std::chrono::steady_clock::now();
  springs.Evaluate(x, held, CurvatureAt(0.0));
  problem.timing->spring_ms += ElapsedMs(start);
  const bool ok = usable(ConjugateGradientStep(problem, forcing, summary));
  if (options_.hessian == HessianChoice::kTrueWithProjectedFallback) springs.Evaluate(x, held, CurvatureAt(1.0));
  return ok;
}

bool InexactNewton::Direction(const MinimizerProblem& problem, const Eigen::VectorXd& x, double forcing,
                              MinimizerSummary* summary) {
  has_negative_direction_ = false;
  SpringSystem& springs = *problem.springs;
  const std::vector<char>& held = *problem.held;
  if (options_.preconditioner == Preconditioner::kLaplacian && problem.laplacian != nullptr &&
      problem.laplacian->ok()) {
    if (LaplacianDirection(problem, x, forcing, summary)) return true;
    return FactorizeAndSolve(problem, x, forcing, summary);
  }
  if (options_.reuse_factorization && !refactor_next_ && problem.linear->FactorCovers(held)) {
    const int cg_before = summary->cg_iterations;
    // The per-spring blocks of the last evaluation are the true Hessian's at x (kAbsolute: its absolute
    // value; kProjected: the projected blocks are evaluated here).
    if (options_.hessian == HessianChoice::kProjected) springs.Evaluate(x, held, CurvatureAt(0.0));
    const auto converged = ConjugateGradientsStatus::kConverged;
    bool ok = ConjugateGradientStep(problem, forcing, summary) == converged;
    if (!ok && options_.hessian == HessianChoice::kTrueWithProjectedFallback) {
      // Negative curvature (compressed springs) or slow progress: the projected Hessian is SPD.
      springs.Evaluate(x, held, CurvatureAt(0.0));
      ok = ConjugateGradientStep(problem, forcing, summary) == converged;
      springs.Evaluate(x, held, CurvatureAt(1.0));
    }
    if (ok && step_.allFinite()) {
      // Conjugate gradients that cost a good part of a factorization say the kept one is stale.
      const double solves = summary->cg_iterations - cg_before;
      if (solves > options_.refactor_cost_ratio * problem.linear->SolvesPerFactorization()) refactor_next_ = true;
      return true;
    }
  }
  return FactorizeAndSolve(problem, x, forcing, summary);
}

void InexactNewton::Minimize(const MinimizerProblem& problem, Eigen::VectorXd* x_ptr, MinimizerSummary* summary) {
  Eigen::VectorXd& x = *x_ptr;
  SpringSystem& springs = *problem.springs;
  const std::vector<char>& held = *problem.held;
  const double diagonal = problem.diagonal;
  step_.resize(x.size());
  trial_.resize(x.size());
  int tiny_steps = 0;
  double last_step = 0.0;  // length of the last Newton step (largest coordinate change)
  MinimizerTiming& timing = *problem.timing;
  auto clock = std::chrono::steady_clock::now();
  double residual = springs.Evaluate(x, held, CurvatureAt(1.0));
  if (summary->iterations == 0) summary->initial_residual = residual;
  double energy = springs.Energy(x);
  timing.spring_ms += ElapsedMs(clock);
  double forcing = kMaxForcing;
  double previous_norm = 0.0;
  summary->termination = MinimizerTermination::kMaxIterations;
  for (int iteration = 0;; ++iteration) {
    if (!std::isfinite(residual) || !std::isfinite(energy)) {
      summary->termination = MinimizerTermination::kNumericalFailure;
      summary->message = "non-finite force or energy";
      break;
    }
    // Converged: the forces are in equilibrium and, if Newton moved at all, its last step was short
    // (a small force alone says little where the system is soft).
    if (residual <= options_.residual_tolerance && last_step <= options_.step_tolerance * diagonal) {
      summary->termination = MinimizerTermination::kConverged;
      break;
    }
    if (problem.Stopped()) {
      summary->termination = MinimizerTermination::kCancelled;
      summary->message = "cancelled";
      break;
    }
    if (iteration >= options_.max_iterations) {
      summary->termination = MinimizerTermination::kMaxIterations;
      summary->message = fmt::format("no convergence in {} Newton iterations", options_.max_iterations);
      break;
    }
    ++summary->iterations;

    // Inexact Newton (Eisenstat-Walker choice 2): solve the linear system only as accurately as the
    // progress of the outer iteration warrants, loosely far from the solution, tightly close to it.
    const double norm = springs.force().norm();
    if (previous_norm > 0.0) {
      const double ratio = norm / previous_norm;
      const double candidate = 0.9 * ratio * ratio;
      const double safeguard = 0.9 * forcing * forcing;
      forcing = std::min(kMaxForcing, safeguard > 0.1 ? std::max(candidate, safeguard) : candidate);
    }
    previous_norm = norm;
    if (!Direction(problem, x, forcing, summary)) {
      summary->termination = MinimizerTermination::kNumericalFailure;
      break;
    }
    // A direction (factorizations, conjugate gradients) is most of an iteration: a stop asked meanwhile ends
    // the solve before its line search, so a cancelled rig build stops within about one direction.
    if (problem.Stopped()) {
      summary->termination = MinimizerTermination::kCancelled;
      summary->message = "cancelled";
      break;
    }

    // A step that carries a vertex further than a fraction of a spring length can pass it through its
    // neighbours and land in another (inverted) equilibrium; shorten such steps before the line search.
    double longest = LongestMove(step_);
    const double max_move = options_.max_step_fraction * problem.mean_rest_length;
    if (longest > max_move) step_ *= max_move / longest;
    if (has_negative_direction_) {
      // On a saddle the projected step barely moves along the unstable mode: add the negative curvature
      // the conjugate gradients met, downhill and as long as a step may be, for the line search to shorten.
      const double d_longest = LongestMove(negative_direction_);
      if (d_longest > 0.0) {
        const double sign = springs.force().dot(negative_direction_) >= 0.0 ? 1.0 : -1.0;
        step_ += (sign * max_move / d_longest) * negative_direction_;
        longest = LongestMove(step_);
        if (longest > max_move) step_ *= max_move / longest;
      }
    }

    LineSearchOptions search;
    search.max_steps = options_.max_line_search_steps;
    clock = std::chrono::steady_clock::now();
    const LineSearchResult found = BacktrackingLineSearch(
        energy, -springs.force().dot(step_), residual, search,
        [&](double t) {
          trial_ = x + t * step_;
          return springs.Energy(trial_);
        },
        [&] { return springs.Evaluate(trial_, held, CurvatureAt(1.0)); });
    summary->line_search_halvings += found.halvings;
    timing.line_search_ms += ElapsedMs(clock);
    if (!found.accepted) {
      springs.Evaluate(x, held, CurvatureAt(1.0));  // restore the forces of the current iterate
      if (residual <= options_.residual_tolerance) {
        // In equilibrium to the tolerance; only the step check could not be completed.
        summary->termination = MinimizerTermination::kConverged;
        break;
      }
      summary->termination = MinimizerTermination::kStalled;
      summary->message = fmt::format("the line search found no lower energy (residual {:.3g})", residual);
      break;
    }
    x.swap(trial_);
    energy = found.energy;
    clock = std::chrono::steady_clock::now();
    residual = found.residual >= 0.0 ? found.residual : springs.Evaluate(x, held, CurvatureAt(1.0));
    timing.spring_ms += ElapsedMs(clock);

    last_step = found.step * step_.lpNorm<Eigen::Infinity>();
    summary->last_step = last_step / diagonal;
    tiny_steps = last_step <= kNoProgress * diagonal ? tiny_steps + 1 : 0;
    if (tiny_steps >= 3 && residual > options_.residual_tolerance) {
      summary->termination = MinimizerTermination::kStalled;
      summary->message = fmt::format("no progress: three steps below {:.0e} of the diagonal with residual {:.3g}",
                                     kNoProgress, residual);
      break;
    }
  }
  summary->residual = residual;
  summary->energy = energy;
}

}  // namespace springblend::internal
