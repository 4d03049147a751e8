// Rigid transforms used by the solve: the canonical gauge frame and Kabsch alignment.
#pragma once

#include <Eigen/Core>
#include <array>

#include "springblend/rig.h"

namespace springblend::internal {

// Moves the stacked positions x (3n) rigidly so that vertex g[0] is at the origin, g[1] on the +x axis
// and g[2] in the xy plane (y >= 0). Returns false if the three are (nearly) collinear.
bool ToCanonicalFrame(const std::array<int, 3>& g, Eigen::VectorXd* x);

// Replaces *points by R * points + t, with the proper rotation R and translation t that best match
// `reference` in the least-squares sense (Kabsch). reference may have fewer rows than *points: the fit
// uses the leading rows (the mesh vertices) and moves all.
void AlignRigidly(const Points& reference, Points* points);

// Tetrahedra (#T by 4 vertex ids, positively oriented at rest) whose signed volume in positions x
// (stacked 3n, or #V by 3) is not positive.
int CountInvertedTetrahedra(const Tetrahedra& tets, const Eigen::VectorXd& x);
int CountInvertedTetrahedra(const Tetrahedra& tets, const Points& x);

}  // namespace springblend::internal
