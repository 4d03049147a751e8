// Backtracking (Armijo) line search on the energy along a descent direction. Near convergence the energy
// change drops below its round-off; there a step is judged by the force it leaves instead.
#pragma once

#include <functional>

namespace springblend::internal {

struct LineSearchOptions {
  int max_steps = 40;                 // halvings before giving up
  double sufficient_decrease = 1e-4;  // Armijo's c1
  double energy_noise = 1e-13;        // relative energy change below round-off
};

struct LineSearchResult {
  bool accepted = false;
  double step = 0.0;      // the accepted fraction t of the direction
  double energy = 0.0;    // E at the accepted point
  double residual = -1.0; // the largest free force there, when the search had to evaluate it (else -1)
  int halvings = 0;
};

// energy_at(t) evaluates E(x + t d) (and may keep that point); residual_at_last() the largest free force
// at the point energy_at last evaluated. `slope` is dE/dt at t = 0 (negative for a descent direction).
LineSearchResult BacktrackingLineSearch(double energy, double slope, double residual,
                                        const LineSearchOptions& options,
                                        const std::function<double(double t)>& energy_at,
                                        const std::function<double()>& residual_at_last);

}  // namespace springblend::internal
