// How several targets combine (SolveOptions::mix). A frame that moves one target is the paper's frame
// whatever the model: rest lengths r̄ = r^0 + w (r^t - r^0) (its in-betweens blending in), solved from the
// target's path. Where several targets act at once:
//
//  - kRestLengths, the paper's blend (section 3.3): r̄ = r^0 + sum_t w_t (r^t - r^0). Every active target's
//    length change adds up: where captured faces move 20-40 expressions at once the mouth's springs get rest
//    lengths far longer than any expression's (the lip seam's 20 times the linear blend's), and the lips buckle
//    into a shape no expression has, a different way from one frame to the next.
//
//  - kSuperposed (the default): the frame's *prediction* is the linear blend plus the targets' own physical
//    corrections at their weights (each the correction its path solved, the target alone; RigOptions::target_paths),
//    averaged per vertex with their magnitudes as weights,
//        y(w) = L(w) + (sum_t c_t(w_t) |c_t(w_t)|) / (sum_t |c_t(w_t)|),
//    and the rest lengths are y's own edge lengths plus a share sigma of the targets' residual strains at their
//    weights (each target's blended rest length less its path's length there: the tension or compression its
//    equilibrium holds), averaged per spring the same way,
//        r̄_q(w) = |y_a - y_b| + sigma (sum_t e_tq |e_tq|) / (sum_t |e_tq|),   e_tq = r̄_q^t(w_t) - |x̃^t_a(w_t) - x̃^t_b(w_t)|,
//    x̃^t(w_t) = L(w_t e_t) + c_t(w_t), and sigma = clamp(2 S_max / sum_t S_t - 1, 0, 1), S_t the size of target t's
//    length changes at its weight (sum_q |w_t (r_q^t - r_q^0)|): 1 while one target changes more lengths than all
//    the others together, 0 once it no longer does.
//    Deltas add as vectors (as the artist sculpted them, and as the linear blend adds them); each target keeps its
//    own physical correction (a jaw's rotation) where it alone corrects a vertex, and where several do the
//    correction is never longer than the longest. Neither length changes, nor corrections, nor strains add up.
//    (Summed, the corrections of a captured face's 20-40 expressions all point the same way at the lips, each
//    restoring its own target's arc: 2.3 % of the diagonal from the linear blend where every expression's own was
//    under 0.7 %. Summed strains put the lips' short springs at 20-30 % and the mix 2-4 % away.)
//    Where no target dominates (sigma 0: every frame of a captured take) the springs rest at y, so y is the
//    answer: its energy is zero, a global minimum, reached without a Newton step and moving with the weights as y
//    does. Colliders and pins then deform that system physically, as in the paper. As one target comes to
//    dominate, its strains come back in: for one target y = x̃^t and r̄ is the paper's exactly, and as a second
//    target's weight goes to 0 the mix goes to that frame continuously.
//
// A sculpted combination (a rig file's corrective driven by the product of its drivers' weights) takes over from
// its drivers' physical corrections and strains as its weight grows (each driver's scaled by 1 - that weight): at
// every driver 1 the sculpt is the answer, as in the paper's blend.
//
// Correctives (targets sculpted to be added to others, as ARKit's mouthClose is for jawOpen: alone it pushes the
// lips through each other) have no physical shape of their own: their correction is not a rotation the linear
// blend loses but a buckle. SolveOptions::linear_targets names them (by default ARKit's); under kSuperposed they add
// as linear deltas (no correction, no residual strain), alone too.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <vector>

#include "anchor.h"
#include "springblend/rig.h"
#include "springblend/solve.h"

namespace springblend::internal {

// Which targets add as linear deltas in this frame's mix (one flag per target): SolveOptions::linear_targets, or
// the default correctives the rig has. Throws Error(kInvalidInput) naming a given name that is no target.
std::vector<char> LinearTargets(const Rig& rig, const SolveOptions& options);

// Whether the frame's rest lengths come from the superposed model: the mix model says so and two or more targets
// move, or the one that moves is a linear target (a single physical target's frame is the paper's in every model).
bool IsSuperposedMix(const SolveOptions& options, const std::vector<char>& linear, const std::vector<double>& weights);

// The frame's prediction y(w) for these target weights: the linear blend of every simulated vertex plus each
// physical target's path correction at its weight (rotated by the anchor's motion), with the vertices the weights
// hold (fixed vertices on the linear blend, the anchor on its blended motion) in place; pins are not part of it.
// use_paths false: the linear blend alone. Stacked 3n.
void Prediction(const Rig& rig, const std::vector<double>& weights, const std::vector<char>& linear, bool use_paths,
                Eigen::VectorXd* y);

// The superposed model's rest lengths for a frame, from its prediction y (Prediction of the same weights): y's
// lengths plus a share of the physical targets' residual strains at their weights averaged per spring with their
// magnitudes as weights (sum s|s| / sum |s|: a target's own strain where it alone strains the spring, at most the
// largest where several do), clamped from below as BlendRestLengths clamps them but never above y's own length
// (y's lengths are the rest lengths where the share is 0). Returns the share (PrestressShare).
double SuperposedRestLengths(const Rig& rig, const std::vector<double>& weights, const std::vector<char>& linear,
                             bool use_paths, const Eigen::VectorXd& y, std::vector<double>* rest_lengths);

}  // namespace springblend::internal
