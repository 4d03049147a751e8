// The backtracking line search on a quadratic, on a non-convex function and where no descent exists.
#include "line_search.h"

#include <gtest/gtest.h>

#include <cmath>

namespace springblend::internal {
namespace {

TEST(LineSearch, TakesTheFullStepOnAQuadraticWhoseMinimumItReaches) {
  // E(t) = (t - 1)^2 along the direction: the Newton step t = 1 is the minimum.
  const auto energy_at = [](double t) { return (t - 1.0) * (t - 1.0); };
  const LineSearchResult r = BacktrackingLineSearch(1.0, -2.0, 1.0, {}, energy_at, [] { return 0.0; });
  EXPECT_TRUE(r.accepted);
  EXPECT_EQ(r.step, 1.0);
  EXPECT_EQ(r.halvings, 0);
  EXPECT_EQ(r.energy, 0.0);
}

TEST(LineSearch, HalvesAnOvershootingStepUntilArmijoHolds) {
  // E(t) = (t - 0.1)^2: a unit step overshoots; Armijo with c1 = 1e-4 accepts t = 0.125.
  const auto energy_at = [](double t) { return (t - 0.1) * (t - 0.1); };
  const double e0 = 0.01, slope = -0.2;
  const LineSearchResult r = BacktrackingLineSearch(e0, slope, 1.0, {}, energy_at, [] { return 0.0; });
  ASSERT_TRUE(r.accepted);
  EXPECT_EQ(r.step, 0.125);
  EXPECT_EQ(r.halvings, 3);
  EXPECT_LE(r.energy, e0 + 1e-4 * r.step * slope);
}

TEST(LineSearch, FindsDescentOnANonConvexFunction) {
  // E(t) = t^4 - t^2 - 0.5 t: concave at 0, a far-away rise for large t.
  const auto energy_at = [](double t) { return std::pow(t * 4.0, 4) - t * t - 0.5 * t; };
  const LineSearchResult r = BacktrackingLineSearch(0.0, -0.5, 1.0, {}, energy_at, [] { return 0.0; });
  ASSERT_TRUE(r.accepted);
  EXPECT_LT(r.energy, 0.0);
  EXPECT_LE(r.energy, 1e-4 * r.step * -0.5);
}

TEST(LineSearch, GivesUpWhenTheDirectionClimbs) {
  const auto energy_at = [](double t) { return 1.0 + t; };
  LineSearchOptions options;
  options.max_steps = 10;
  const LineSearchResult r = BacktrackingLineSearch(1.0, 1.0, 1.0, options, energy_at, [] { return 2.0; });
  EXPECT_FALSE(r.accepted);
  EXPECT_EQ(r.halvings, 10);
}

TEST(LineSearch, BelowRoundOffJudgesAStepByTheForceItLeaves) {
  // The energy does not change measurably; the step is taken because the residual falls.
  const auto energy_at = [](double) { return 1.0; };
  const LineSearchResult r = BacktrackingLineSearch(1.0, -1e-10, 1e-6, {}, energy_at, [] { return 1e-7; });
  EXPECT_TRUE(r.accepted);
  EXPECT_EQ(r.residual, 1e-7);
  LineSearchOptions few;
  few.max_steps = 3;  // (with many halvings t * slope itself drops below round-off and Armijo holds)
  const LineSearchResult worse = BacktrackingLineSearch(1.0, -1e-10, 1e-6, few, energy_at, [] { return 1e-5; });
  EXPECT_FALSE(worse.accepted);
}

}  // namespace
}  // namespace springblend::internal
