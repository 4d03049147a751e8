// A frame's boundary conditions (paper section 3.4): fixed vertices follow the linear blend, the anchor its
// blended rigid motion, pins their positions; a rig that none of them holds is solved in the frame of a
// 3-2-1 gauge. Shared by the per-frame solve and the rig's target paths.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <utility>
#include <vector>

#include "anchor.h"
#include "springblend/rig.h"

namespace springblend::internal {

struct FrameConditions {
  std::vector<std::pair<int, Eigen::Vector3d>> held;  // vertex, position (later entries win)
  std::optional<AnchorMotion> motion;                 // the anchor's blended motion (anchored rigs)
  BoundaryMode mode = BoundaryMode::kFloating;        // how this frame's rigid motion is pinned down
  double diagonal_shift = 0.0;                        // removes the free rotation of a partly held rig
};

// `weights`: one per sculpted shape (Rig::ShapeWeights); `linear`: the linear blend of every simulated vertex
// for them; `pins`: vertex and position.
FrameConditions ConditionsOf(const Rig& rig, const std::vector<double>& weights, const Points& linear,
                             const std::vector<std::pair<int, Eigen::Vector3d>>& pins);

// Puts the held vertices into the start x (stacked 3n) and marks them in *held (reset first); a floating
// frame is moved into its gauge's frame. False if the gauge's vertices are collinear in x.
bool HoldConditions(const Rig& rig, const FrameConditions& conditions, Eigen::VectorXd* x, std::vector<char>* held);

}  // namespace springblend::internal
