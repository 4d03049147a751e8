// The paper's internal anchor (section 3.4): a small rigid set of interior vertices whose motion is a
// blended rigid transform, fixed as boundary conditions while the rest of the system relaxes.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <vector>

#include "springblend/mesh.h"

namespace springblend::internal {

// A rigid motion about the anchor's rest centroid c: p -> rotation * (p - c) + c + offset.
struct AnchorMotion {
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Eigen::Vector3d offset = Eigen::Vector3d::Zero();

  Eigen::Vector3d Apply(const Eigen::Vector3d& p, const Eigen::Vector3d& centroid) const {
    return rotation * (p - centroid) + centroid + offset;
  }
};

// The best rigid motion (Kabsch) taking `from` onto `to` (same rows), expressed about from's centroid.
AnchorMotion FitRigidMotion(const Points& from, const Points& to);

// Blends the targets' anchor motions with the rig's weights (the rest shape's motion is the identity with
// weight 1 - sum). One active target: the rotation is the identity raised to the weight along the geodesic
// (slerp, which also extrapolates); several: the normalized weighted quaternion average. Offsets blend
// linearly.
AnchorMotion BlendAnchorMotions(const std::vector<AnchorMotion>& targets, const std::vector<double>& weights);

// Picks an anchor among `candidates` (interior vertex ids into `points`): the candidate nearest `center`
// and its nearest fellow candidates, `size` in all, such that they span 3D when possible (at least a plane).
// Returns an empty list if fewer than three non-collinear candidates exist.
std::vector<int> ChooseAnchor(const Points& points, const std::vector<int>& candidates,
                              const Eigen::Vector3d& center, int size);

}  // namespace springblend::internal
