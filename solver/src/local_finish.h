// A frame whose start is already in balance almost everywhere (a single-target frame from its dense target
// path) is finished where it is out of balance only: Newton on the vertices whose force exceeds the tolerance
// and a ring around them, every other vertex held at the start; the region grows around any held vertex whose
// force exceeds the tolerance, until none does, by one ring after the first round and twice as many rings
// after each round after it (an imbalance that crossed the region's edge once spreads further the next time).
// The frame then passes the same convergence test as a full solve (largest free force and last Newton step) on
// every free coordinate, so a local finish certifies the same stationary point a full solve would. It gives up
// (the caller solves the whole frame) when the region outgrows a share of the vertices, or Newton does not
// converge in it.
#pragma once

#include <Eigen/Core>
#include <functional>
#include <string>
#include <vector>

#include "spring_system.h"
#include "springblend/rig.h"

namespace springblend::internal {

struct LocalFinishOptions {
  double residual_tolerance = 1e-6;  // largest free force (strain units), as the full solve's
  double step_tolerance = 1e-5;      // last step, fraction of the diagonal, as the full solve's
  double max_step_fraction = 2.0;    // of the mean rest length, per vertex and step
  int max_line_search_steps = 40;
  int max_iterations = 15;           // Newton iterations over all rounds
  int max_rounds = 6;                // region growths
  double max_share = 0.3;            // of the free vertices; beyond it a full solve is cheaper
  // Gives up at once, x untouched, when more than this share of the free vertices starts out of balance (for
  // a caller with a cheaper remedy for such a start: the path span step).
  double max_seed_share = 1.0;
  // The backend that factors the region's Hessian for its direct solves (a double-precision one: CHOLMOD's
  // supernodal factorization is several times faster than a simplicial one on regions of a few thousand
  // vertices).
  LinearSolverType linear_solver = LinearSolverType::kCholmodSupernodal;
};

// The backend that factors a region for a rig solved with `rig_solver`: MUMPS here is single precision (and one
// lock serialises it across threads), so a MUMPS rig's regions are factored by CHOLMOD; any other backend factors
// its own.
inline LinearSolverType RegionLinearSolver(LinearSolverType rig_solver) {
  return rig_solver == LinearSolverType::kMumpsSingle ? LinearSolverType::kCholmodSupernodal : rig_solver;
}

struct LocalFinishResult {
  bool converged = false;
  int vertices = 0;      // in the final region (0: the start was in balance already)
  int free_vertices = 0; // vertices with a free coordinate
  int rounds = 0;
  int iterations = 0;
  int factorizations = 0;
  int projected_factorizations = 0;
  int line_search_halvings = 0;
  double initial_residual = 0.0;
  double residual = 0.0;   // largest free force over every free coordinate, after
  double last_step = 0.0;  // fraction of the diagonal
  std::string why;         // why it gave up
};

// Lowers the energy of *x in regions around its out-of-balance vertices. `springs` holds the frame's rest
// lengths; `held` its held coordinates (3n); `diagonal_shift` is added on the free diagonal (a partly held
// rig's tiny shift). *x only ever moves to lower energy, so the caller may go on from it.
LocalFinishResult LocalFinish(SpringSystem* springs, const std::vector<char>& held, double diagonal_shift,
                              double diagonal, double mean_rest_length, const LocalFinishOptions& options,
                              const std::function<bool()>* stop, Eigen::VectorXd* x);

}  // namespace springblend::internal
