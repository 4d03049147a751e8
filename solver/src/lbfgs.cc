#include "lbfgs.h"

#include <fmt/format.h>

#include <chrono>
#include <cmath>

#include "laplacian.h"
#include "line_search.h"

namespace springblend::internal {

void Lbfgs::Direction(const MinimizerProblem& problem, const Eigen::VectorXd& gradient, Eigen::VectorXd* direction) {
  q_ = gradient;
  alpha_.resize(pairs_.size());
  for (size_t i = pairs_.size(); i-- > 0;) {
    alpha_[i] = pairs_[i].rho * pairs_[i].s.dot(q_);
    q_ -= alpha_[i] * pairs_[i].y;
  }
  const auto start = std::chrono::steady_clock::now();
  problem.laplacian->Apply(q_, *problem.held, &z_);
  problem.timing->solve_ms += ElapsedMs(start);
  for (size_t i = 0; i < pairs_.size(); ++i) {
    const double beta = pairs_[i].rho * pairs_[i].y.dot(z_);
    z_ += (alpha_[i] - beta) * pairs_[i].s;
  }
  *direction = -z_;
}

void Lbfgs::Minimize(const MinimizerProblem& problem, Eigen::VectorXd* x_ptr, MinimizerSummary* summary) {
  if (problem.laplacian == nullptr || !problem.laplacian->ok()) {
    newton_.Minimize(problem, x_ptr, summary);
    return;
  }
  Eigen::VectorXd& x = *x_ptr;
  SpringSystem& springs = *problem.springs;
  const std::vector<char>& held = *problem.held;
  const double diagonal = problem.diagonal;
  const Curvature curvature{1.0, false};
  pairs_.clear();
  MinimizerTiming& timing = *problem.timing;
  auto clock = std::chrono::steady_clock::now();
  double residual = springs.Evaluate(x, held, curvature, false);
  double energy = springs.Energy(x);
  timing.spring_ms += ElapsedMs(clock);
  if (summary->iterations == 0) summary->initial_residual = residual;
  Eigen::VectorXd gradient = -springs.force(), direction, trial, previous_gradient;
  double last_step = 0.0;
  int own_iterations = 0;
  summary->termination = MinimizerTermination::kMaxIterations;
  bool hand_over = false;
  for (;;) {
    if (!std::isfinite(residual) || !std::isfinite(energy)) {
      summary->termination = MinimizerTermination::kNumericalFailure;
      summary->message = "non-finite force or energy";
      break;
    }
    if (residual <= options_.residual_tolerance && last_step <= options_.step_tolerance * diagonal) {
      summary->termination = MinimizerTermination::kConverged;
      break;
    }
    if (problem.Stopped()) {
      summary->termination = MinimizerTermination::kCancelled;
      summary->message = "cancelled";
      break;
    }
    if (summary->iterations >= options_.max_iterations) {
      summary->termination = MinimizerTermination::kMaxIterations;
      summary->message = fmt::format("no convergence in {} iterations", options_.max_iterations);
      break;
    }
    if (own_iterations >= options_.lbfgs_max_iterations) {
      hand_over = true;
      break;
    }
    ++summary->iterations;
    ++summary->lbfgs_iterations;
    ++own_iterations;
    Direction(problem, gradient, &direction);
    double slope = gradient.dot(direction);
    if (!(slope < 0.0)) {  // not a descent direction: forget the history
      pairs_.clear();
      Direction(problem, gradient, &direction);
      slope = gradient.dot(direction);
      if (!(slope < 0.0)) {
        hand_over = true;
        break;
      }
    }
    const double max_move = options_.max_step_fraction * problem.mean_rest_length;
    const double longest = LongestMove(direction);
    if (longest > max_move) {
      direction *= max_move / longest;
      slope *= max_move / longest;
    }
    clock = std::chrono::steady_clock::now();
    LineSearchOptions search;
    search.max_steps = options_.max_line_search_steps;
    const LineSearchResult found = BacktrackingLineSearch(
        energy, slope, residual, search,
        [&](double t) {
          trial = x + t * direction;
          return springs.Energy(trial);
        },
        [&] { return springs.Evaluate(trial, held, curvature, false); });
    summary->line_search_halvings += found.halvings;
    timing.line_search_ms += ElapsedMs(clock);
    if (!found.accepted) {
      hand_over = true;
      break;
    }
    clock = std::chrono::steady_clock::now();
    previous_gradient.swap(gradient);
    Pair pair{trial - x, Eigen::VectorXd(), 0.0};
    x.swap(trial);
    energy = found.energy;
    residual = found.residual >= 0.0 ? found.residual : springs.Evaluate(x, held, curvature, false);
    timing.spring_ms += ElapsedMs(clock);
    gradient = -springs.force();
    pair.y = gradient - previous_gradient;
    const double ys = pair.y.dot(pair.s);
    if (ys > 1e-10 * pair.s.norm() * pair.y.norm() && ys > 0.0) {
      pair.rho = 1.0 / ys;
      pairs_.push_back(std::move(pair));
      if (static_cast<int>(pairs_.size()) > options_.lbfgs_history) pairs_.pop_front();
    }
    last_step = found.step * direction.lpNorm<Eigen::Infinity>();
    summary->last_step = last_step / diagonal;
  }
  summary->residual = residual;
  summary->energy = energy;
  if (hand_over) {
    // Newton finishes from here (its own termination, counts and message).
    ++summary->newton_fallbacks;
    newton_.Minimize(problem, x_ptr, summary);
  }
}

}  // namespace springblend::internal
