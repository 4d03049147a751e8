#include "rigid.h"

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <Eigen/SVD>

namespace springblend::internal {

bool ToCanonicalFrame(const std::array<int, 3>& g, Eigen::VectorXd* x) {
  Eigen::VectorXd& v = *x;
  const Eigen::Vector3d origin = v.segment<3>(3 * g[0]);
  const Eigen::Vector3d axis = v.segment<3>(3 * g[1]) - origin;
  const Eigen::Vector3d in_plane = v.segment<3>(3 * g[2]) - origin;
  const Eigen::Vector3d normal = axis.cross(in_plane);
  if (axis.norm() == 0.0 || normal.norm() <= 1e-12 * axis.squaredNorm()) return false;
  Eigen::Matrix3d rotation;
  rotation.row(0) = axis.normalized();
  rotation.row(2) = normal.normalized();
  rotation.row(1) = rotation.row(2).cross(rotation.row(0));
  const Eigen::Index n = v.size() / 3;
  for (Eigen::Index i = 0; i < n; ++i) v.segment<3>(3 * i) = rotation * (v.segment<3>(3 * i) - origin);
  // Exact zeros for the held coordinates, so they carry no round-off into the solve.
  v[3 * g[0]] = v[3 * g[0] + 1] = v[3 * g[0] + 2] = 0.0;
  v[3 * g[1] + 1] = v[3 * g[1] + 2] = 0.0;
  v[3 * g[2] + 2] = 0.0;
  return true;
}

void AlignRigidly(const Points& reference, Points* points) {
  // Kabsch on the leading rows; the fit moves every row.
  Points& p = *points;
  const Eigen::Matrix4d fit = Eigen::umeyama(p.topRows(reference.rows()).transpose(), reference.transpose(), false);
  p = (p * fit.topLeftCorner<3, 3>().transpose()).rowwise() + fit.topRightCorner<3, 1>().transpose();
}

namespace {
template <typename Position>
int CountInverted(const Tetrahedra& tets, Position position) {
  int inverted = 0;
  for (Eigen::Index t = 0; t < tets.rows(); ++t) {
    const Eigen::Vector3d p0 = position(tets(t, 0));
    const double volume =
        (position(tets(t, 1)) - p0).dot((position(tets(t, 2)) - p0).cross(position(tets(t, 3)) - p0));
    if (volume <= 0.0) ++inverted;
  }
  return inverted;
}
}  // namespace

int CountInvertedTetrahedra(const Tetrahedra& tets, const Eigen::VectorXd& x) {
  return CountInverted(tets, [&](int v) -> Eigen::Vector3d { return x.segment<3>(3 * v); });
}

int CountInvertedTetrahedra(const Tetrahedra& tets, const Points& x) {
  return CountInverted(tets, [&](int v) -> Eigen::Vector3d { return x.row(v).transpose(); });
}

}  // namespace springblend::internal
