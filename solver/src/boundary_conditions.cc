#include "boundary_conditions.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

#include "rigid.h"

namespace springblend::internal {

Span SpanOf(const std::vector<Eigen::Vector3d>& points, int first) {
  Span span;
  span.ids[0] = first;
  const Eigen::Vector3d& p0 = points[first];
  double best = -1.0;
  for (size_t i = 0; i < points.size(); ++i) {
    const double d = (points[i] - p0).squaredNorm();
    if (d > best) best = d, span.ids[1] = static_cast<int>(i);
  }
  const Eigen::Vector3d axis = (points[span.ids[1]] - p0).normalized();
  best = -1.0;
  for (size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector3d r = points[i] - p0;
    const double d = (r - r.dot(axis) * axis).squaredNorm();
    if (d > best) best = d, span.ids[2] = static_cast<int>(i);
  }
  span.off_line = std::sqrt(std::max(best, 0.0));
  return span;
}

bool SpansRigidly(const std::vector<Eigen::Vector3d>& points, double scale) {
  if (points.size() < 3) return false;
  const Span span = SpanOf(points, 0);
  if ((points[span.ids[1]] - points[0]).norm() <= 1e-9 * scale) return false;
  return span.off_line > 1e-6 * scale;
}

bool HoldGauge(const std::array<int, 3>& g, Eigen::VectorXd* x, std::vector<char>* held) {
  if (!ToCanonicalFrame(g, x)) return false;
  std::vector<char>& fixed = *held;
  fixed[3 * g[0]] = fixed[3 * g[0] + 1] = fixed[3 * g[0] + 2] = 1;
  fixed[3 * g[1] + 1] = fixed[3 * g[1] + 2] = 1;
  fixed[3 * g[2] + 2] = 1;
  return true;
}

}  // namespace springblend::internal
