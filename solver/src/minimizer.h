// A minimizer lowers a frame's spring energy with some coordinates held, from a start to an equilibrium.
// The Solver (and the rig builder's placement solves) pick one by its type; each is built from the small
// parts beside it (spring system, linear system, conjugate gradients, line search).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <chrono>
#include <functional>
#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "linear_system.h"
#include "spring_system.h"

namespace springblend::internal {

enum class MinimizerType {
  kInexactNewton,  // Newton steps by preconditioned conjugate gradients (see Preconditioner)
  kLbfgs,          // L-BFGS with the scalar Laplacian as initial Hessian, finished by Newton on a stall
};

// What preconditions inexact Newton's conjugate gradients.
enum class Preconditioner {
  kKeptFactor,  // the last 3n x 3n factorization of the Hessian, refactored when it stops paying off
  kLaplacian,   // the solver's scalar n x n Laplacian (laplacian.h): no 3n factorization unless CG fails
};

enum class HessianChoice {
  kTrueWithProjectedFallback,  // the true Hessian while its Cholesky succeeds, else the projected one
  kProjected,                  // always clamp compressed springs' transverse term at zero
  kAbsolute,                   // always its absolute value
};

struct MinimizerOptions {
  MinimizerType type = MinimizerType::kInexactNewton;
  double residual_tolerance = 1e-6;  // largest free force (strain units)
  double step_tolerance = 1e-5;      // last step, fraction of the diagonal
  int max_iterations = 200;
  int max_line_search_steps = 40;
  HessianChoice hessian = HessianChoice::kTrueWithProjectedFallback;
  bool reuse_factorization = true;   // false: a fresh factorization and a direct solve every iteration
  int max_cg_iterations = 40;
  double refactor_cost_ratio = 0.5;
  bool follow_negative_curvature = false;
  double max_step_fraction = 2.0;    // of the mean rest length, per vertex and step
  Preconditioner preconditioner = Preconditioner::kKeptFactor;
  int lbfgs_history = 10;            // (s, y) pairs kept
  int lbfgs_max_iterations = 100;    // before Newton takes over
};

enum class MinimizerTermination { kConverged, kMaxIterations, kStalled, kNumericalFailure, kCancelled };

// Counts add up over calls (a frame's contact rounds); the termination and message are the last call's.
struct MinimizerSummary {
  MinimizerTermination termination = MinimizerTermination::kNumericalFailure;
  std::string message;
  int iterations = 0;
  int factorizations = 0;
  int projected_factorizations = 0;
  int shifted_factorizations = 0;
  int line_search_halvings = 0;
  int cg_iterations = 0;
  double initial_residual = 0.0;
  double residual = 0.0;
  double last_step = 0.0;  // fraction of the diagonal
  double energy = 0.0;
  double factorize_ms = 0.0;
  int lbfgs_iterations = 0;
  int newton_fallbacks = 0;  // L-BFGS handed the frame to Newton
};

// Where a frame's time went (ms), added to by every part.
struct MinimizerTiming {
  double spring_ms = 0.0;       // energy, force and Hessian-block passes outside the line search
  double solve_ms = 0.0;        // linear solves: conjugate gradients (with their Hessian products), direct solves
  double line_search_ms = 0.0;  // energy (and force) evaluations of trial points
  double factorize_ms = 0.0;    // numeric factorizations with their assembly
};

class LaplacianPreconditioner;

// Milliseconds since a point in time (the minimizers' time split).
inline double ElapsedMs(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

// The longest move of one vertex in a stacked 3n step (steps are clamped by it).
inline double LongestMove(const Eigen::VectorXd& step) {
  double longest = 0.0;
  for (Eigen::Index v = 0; v < step.size() / 3; ++v) longest = std::max(longest, step.segment<3>(3 * v).squaredNorm());
  return std::sqrt(longest);
}

// One frame's problem: its springs (rest lengths set), held coordinates and their linear algebra.
struct MinimizerProblem {
  SpringSystem* springs = nullptr;
  LinearSystem* linear = nullptr;
  const std::vector<char>* held = nullptr;  // 3n, 1 = held
  double diagonal_shift = 0.0;              // added to the free diagonal (a tiny one removes a null space)
  double diagonal = 1.0;                    // bounding-box diagonal: the length scale of steps
  double mean_rest_length = 1.0;
  LaplacianPreconditioner* laplacian = nullptr;  // for the methods that use it
  MinimizerTiming* timing = nullptr;              // never null
  const std::function<bool()>* stop = nullptr;    // asked once per iteration; true ends with kCancelled

  bool Stopped() const { return stop != nullptr && *stop && (*stop)(); }
};

class Minimizer {
 public:
  virtual ~Minimizer() = default;
  // Lowers the energy from *x (held coordinates already in place) and adds to *summary.
  virtual void Minimize(const MinimizerProblem& problem, Eigen::VectorXd* x, MinimizerSummary* summary) = 0;
  // New options of the same type; what the minimizer learnt about the problem (a kept factor) stays.
  virtual void SetOptions(const MinimizerOptions& options) = 0;
  virtual MinimizerType type() const = 0;
  // Forget what was learnt from earlier problems, so the next Minimize depends on its problem alone.
  virtual void Reset() = 0;
  static std::unique_ptr<Minimizer> Create(const MinimizerOptions& options);
};

}  // namespace springblend::internal
