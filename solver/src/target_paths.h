// Each target's own path, for stateless frames: at rig build, the equilibria of alpha * target for alpha
// sampled over [-extension, 1 + extension], each solved by continuation from the one before (the paper's
// sweep) up from the rest shape and, when that does not end on the target, down from the target, keeping at
// each alpha the one of lower energy (so alpha 0 and 1 are the rest shape and the target exactly), and kept as the physical correction (solved
// minus linear blend) in the anchor's frame. A frame starts
// from the linear blend plus each active target's correction at its weight: a single-target frame starts on
// the branch the sweep follows, any frame starts close to its answer, and the answer is a function of the
// frame alone.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <vector>

#include "anchor.h"
#include "springblend/rig.h"

namespace springblend::internal {

struct TargetPath {
  double step = 0.0;  // alpha between samples
  int first = 0;      // sample k is at alpha = (first + k) * step
  std::vector<Eigen::MatrixXf> corrections;  // per sample: #vertices by 3, in the anchor's frame
  bool empty() const { return corrections.empty(); }
};

struct TargetPathsReport {
  int samples = 0;      // equilibria solved
  int unconverged = 0;  // samples whose solve did not converge (kept as the best found)
  int newton_iterations = 0;
  double ms = 0.0;
};

// Solves every target's path: `intervals` samples per unit of alpha, `extension` beyond [0, 1] on both
// sides. Targets run in parallel. Targets that change no rest length get an empty path.
std::vector<TargetPath> BuildTargetPaths(const Rig& rig, int intervals, double extension, TargetPathsReport* report);

// x += sum_t R correction_t(w_t), stacked 3n: each path interpolated (Catmull-Rom) at its weight (held at
// its end sample beyond the sampled range), rotated by the frame's anchor rotation R.
void AddPathCorrections(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                        const std::optional<AnchorMotion>& motion, Eigen::VectorXd* x);

}  // namespace springblend::internal
