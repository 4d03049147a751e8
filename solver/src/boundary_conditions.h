// Boundary conditions: which points pin down a spring system's rigid motion, and the 3-2-1 gauge that
// holds a floating one without adding a force. Shared by the rig builder and the per-frame solve.
#pragma once

#include <Eigen/Core>
#include <array>
#include <vector>

namespace springblend::internal {

// Three of `points` that span them: the one at `first`, the farthest from it, and the farthest from the
// line through those two; off_line is that last distance.
struct Span {
  std::array<int, 3> ids = {-1, -1, -1};
  double off_line = 0.0;
};
Span SpanOf(const std::vector<Eigen::Vector3d>& points, int first);

// Whether holding these points removes every rigid motion: three or more, not all on one line (within
// 1e-6 of `scale`).
bool SpansRigidly(const std::vector<Eigen::Vector3d>& points, double scale);

// Holds the 3-2-1 gauge on vertices g: moves the stacked positions x rigidly so that g[0] is at the origin,
// g[1] on the +x axis and g[2] in the xy plane, and marks those six coordinates held. False if the three
// are (nearly) collinear in x.
bool HoldGauge(const std::array<int, 3>& g, Eigen::VectorXd* x, std::vector<char>* held);

}  // namespace springblend::internal
