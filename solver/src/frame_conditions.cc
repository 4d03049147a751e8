#include "frame_conditions.h"

#include <algorithm>

#include "boundary_conditions.h"
#include "rig_internals.h"

namespace springblend::internal {

FrameConditions ConditionsOf(const Rig& rig, const std::vector<double>& weights, const Points& linear,
                             const std::vector<std::pair<int, Eigen::Vector3d>>& pins) {
  FrameConditions c;
  for (int v : rig.fixed_vertices()) c.held.emplace_back(v, linear.row(v).transpose());
  if (rig.boundary_mode() == BoundaryMode::kAnchored) {
    c.motion = BlendAnchorMotions(rig.internals().anchor_motions, weights);
    for (int v : rig.anchor_vertices()) {
      c.held.emplace_back(v, c.motion->Apply(rig.shape(0).row(v).transpose(), rig.anchor_centroid()));
    }
  }
  c.held.insert(c.held.end(), pins.begin(), pins.end());
  c.mode = rig.boundary_mode();
  if (c.mode != BoundaryMode::kAnchored && c.mode != BoundaryMode::kFixedVertices) {
    std::vector<Eigen::Vector3d> points;
    for (const auto& h : c.held) points.push_back(h.second);
    c.mode = SpansRigidly(points, rig.summary().bounding_box_diagonal) ? BoundaryMode::kFixedVertices
             : c.held.empty()                                         ? BoundaryMode::kFloating
                                                                      : BoundaryMode::kPartiallyFixed;
  }
  if (c.mode == BoundaryMode::kPartiallyFixed) c.diagonal_shift = 1e-8 / rig.summary().mean_rest_length;
  return c;
}

bool HoldConditions(const Rig& rig, const FrameConditions& conditions, Eigen::VectorXd* x, std::vector<char>* held) {
  std::fill(held->begin(), held->end(), 0);
  for (const auto& [v, p] : conditions.held) {
    x->segment<3>(3 * v) = p;
    (*held)[3 * v] = (*held)[3 * v + 1] = (*held)[3 * v + 2] = 1;
  }
  if (conditions.mode == BoundaryMode::kFloating) return HoldGauge(rig.gauge_vertices(), x, held);
  return true;
}

}  // namespace springblend::internal
