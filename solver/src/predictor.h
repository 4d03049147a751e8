// Where a frame's Newton solve starts. Without history, the linear blendshape. With the previous frames
// of a sequence: their equilibrium carried along with the anchor's motion, and, when the weights keep moving
// along one line (a sweep, a dragged slider), the polynomial through the last two or three solutions
// (secant or quadratic predictor), so Newton starts O(h^2) or O(h^3) rather than O(h) away.
#pragma once

#include <Eigen/Core>
#include <deque>
#include <functional>
#include <optional>
#include <utility>
#include <vector>

#include "anchor.h"
#include "springblend/mesh.h"

namespace springblend::internal {

class Predictor {
 public:
  // How many past frames the highest-order predictor uses.
  static constexpr size_t kFrames = 3;

  void Reset() { past_.clear(); }
  // Start the next frame from these positions (#vertices by 3), with no history for extrapolation.
  void SetStart(const Points& positions);
  // Remembers a solved frame; `node`: it converged, so the polynomial may pass through it.
  void Add(const Points& positions, const std::optional<AnchorMotion>& motion, const std::vector<double>& weights,
           bool node);
  bool empty() const { return past_.empty(); }

  // Writes the start (stacked, 3n) for a frame with these weights, anchor motion (about `centroid`) and held
  // vertices. With no history (or warm starts off) the start is `linear`. `energy` scores candidates: where
  // the path bends sharply a higher order can overshoot, so the one with the least spring energy wins.
  void Predict(const Points& linear, const std::optional<AnchorMotion>& motion, const Eigen::Vector3d& centroid,
               const std::vector<double>& weights, const std::vector<std::pair<int, Eigen::Vector3d>>& held,
               bool extrapolate, const std::function<double(const Eigen::VectorXd&)>& energy,
               Eigen::VectorXd* start) const;

 private:
  struct PastFrame {
    Points positions;
    std::optional<AnchorMotion> motion;
    std::vector<double> weights;  // empty for SetStart
    bool node;
  };
  std::deque<PastFrame> past_;  // newest first, consecutive frames only
};

}  // namespace springblend::internal
