#include "line_search.h"

#include <algorithm>

namespace springblend::internal {

LineSearchResult BacktrackingLineSearch(double energy, double slope, double residual,
                                        const LineSearchOptions& options,
                                        const std::function<double(double t)>& energy_at,
                                        const std::function<double()>& residual_at_last) {
  LineSearchResult result;
  const double noise = options.energy_noise * std::max(energy, 1e-300);
  double t = 1.0;
  for (int k = 0; k < options.max_steps && !result.accepted; ++k) {
    result.residual = -1.0;
    const double trial = energy_at(t);
    result.energy = trial;
    if (trial <= energy + options.sufficient_decrease * t * slope) {
      result.accepted = true;
    } else if (trial - energy <= noise) {
      result.residual = residual_at_last();
      result.accepted = result.residual < residual;
    }
    if (!result.accepted) {
      t *= 0.5;
      ++result.halvings;
    }
  }
  result.step = result.accepted ? t : 0.0;
  return result;
}

}  // namespace springblend::internal
