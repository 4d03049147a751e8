#include "anchor.h"

#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <numeric>

namespace springblend::internal {

AnchorMotion FitRigidMotion(const Points& from, const Points& to) {
  // Kabsch: the least-squares rotation and translation (no scaling) taking from onto to.
  const Eigen::Matrix4d fit = Eigen::umeyama(from.transpose(), to.transpose(), false);
  AnchorMotion motion;
  motion.rotation = Eigen::Quaterniond(Eigen::Matrix3d(fit.topLeftCorner<3, 3>())).normalized();
  motion.offset = (to.colwise().mean() - from.colwise().mean()).transpose();
  return motion;
}

AnchorMotion BlendAnchorMotions(const std::vector<AnchorMotion>& targets, const std::vector<double>& weights) {
  AnchorMotion blended;
  int active = 0, last = -1;
  double rest_weight = 1.0;
  for (size_t t = 0; t < targets.size(); ++t) {
    blended.offset += weights[t] * targets[t].offset;
    rest_weight -= weights[t];
    if (weights[t] != 0.0) ++active, last = static_cast<int>(t);
  }
  if (active == 0) return blended;
  if (active == 1) {
    // Along the geodesic from the identity: q^w.
    const Eigen::AngleAxisd axis_angle(targets[last].rotation);
    blended.rotation = Eigen::Quaterniond(Eigen::AngleAxisd(weights[last] * axis_angle.angle(), axis_angle.axis()));
    return blended;
  }
  // Normalized weighted average, each quaternion on the identity's hemisphere (q and -q are one rotation).
  Eigen::Vector4d sum = rest_weight * Eigen::Quaterniond::Identity().coeffs();
  for (size_t t = 0; t < targets.size(); ++t) {
    Eigen::Vector4d q = targets[t].rotation.coeffs();
    if (q.w() < 0.0) q = -q;  // coeffs() is (x, y, z, w)
    sum += weights[t] * q;
  }
  if (sum.norm() > 1e-12) blended.rotation = Eigen::Quaterniond(sum / sum.norm());
  return blended;
}

std::vector<int> ChooseAnchor(const Points& points, const std::vector<int>& candidates,
                              const Eigen::Vector3d& center, int size) {
  if (candidates.size() < 3) return {};
  std::vector<int> order(candidates);
  std::sort(order.begin(), order.end(), [&](int a, int b) {
    return (points.row(a).transpose() - center).squaredNorm() < (points.row(b).transpose() - center).squaredNorm();
  });
  const Eigen::Vector3d first = points.row(order[0]).transpose();
  std::sort(order.begin() + 1, order.end(), [&](int a, int b) {
    return (points.row(a).transpose() - first).squaredNorm() < (points.row(b).transpose() - first).squaredNorm();
  });
  // Grow until the set is at least planar and has `size` members (or the candidates run out).
  std::vector<int> anchor;
  for (int id : order) {
    anchor.push_back(id);
    if (static_cast<int>(anchor.size()) < std::max(size, 3)) continue;
    Points p(static_cast<Eigen::Index>(anchor.size()), 3);
    for (size_t i = 0; i < anchor.size(); ++i) p.row(static_cast<Eigen::Index>(i)) = points.row(anchor[i]);
    const Eigen::RowVector3d mean = p.colwise().mean();
    Eigen::JacobiSVD<Eigen::MatrixXd> svd((p.rowwise() - mean), Eigen::ComputeThinV);
    const auto& s = svd.singularValues();
    if (s(1) > 1e-3 * s(0)) return anchor;  // not collinear
  }
  return {};
}

}  // namespace springblend::internal
