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
  Points& p = *points;
  const auto fitted = p.topRows(reference.rows());
  const Eigen::RowVector3d p_mean = fitted.colwise().mean();
  const Eigen::RowVector3d r_mean = reference.colwise().mean();
  const Eigen::Matrix3d covariance =
      (fitted.rowwise() - p_mean).transpose() * (reference.rowwise() - r_mean);
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(covariance, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d correction = Eigen::Matrix3d::Identity();
  if ((svd.matrixV() * svd.matrixU().transpose()).determinant() < 0.0) correction(2, 2) = -1.0;
  const Eigen::Matrix3d rotation = svd.matrixV() * correction * svd.matrixU().transpose();
  p = ((p.rowwise() - p_mean) * rotation.transpose()).rowwise() + r_mean;
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
