#include "predictor.h"

namespace springblend::internal {

void Predictor::SetStart(const Points& positions) {
  past_.clear();
  past_.push_front(PastFrame{positions, std::nullopt, {}, false});
}

void Predictor::Add(const Points& positions, const std::optional<AnchorMotion>& motion,
                    const std::vector<double>& weights, bool node) {
  past_.push_front(PastFrame{positions, motion, weights, node});
  if (past_.size() > kFrames) past_.pop_back();
}

void Predictor::Predict(const Points& linear, const std::optional<AnchorMotion>& motion,
                        const Eigen::Vector3d& c, const std::vector<double>& weights,
                        const std::vector<std::pair<int, Eigen::Vector3d>>& held, bool extrapolate,
                        const std::function<double(const Eigen::VectorXd&)>& energy,
                        Eigen::VectorXd* start) const {
  const int n = static_cast<int>(linear.rows());
  Eigen::VectorXd& x = *start;
  x.resize(3 * n);
  if (past_.empty()) {
    for (int v = 0; v < n; ++v) x.segment<3>(3 * v) = linear.row(v).transpose();
    return;
  }
  // Coordinates in the frame of an anchor motion (identity without an anchor), and back.
  const auto to_local = [&](const Eigen::Vector3d& p, const std::optional<AnchorMotion>& m) {
    return m ? Eigen::Vector3d(m->rotation.inverse() * (p - c - m->offset)) : p;
  };
  const auto to_world = [&](const Eigen::Vector3d& l) {
    return motion ? Eigen::Vector3d(motion->rotation * l + c + motion->offset) : l;
  };
  const bool anchored = motion.has_value() && past_[0].motion.has_value();

  // Nodes of the predictor: the positions t_k of the past frames' weights on the line from the previous
  // weights (t = 0) to this frame's (t = 1). A past frame joins while its weights lie on that line (within
  // about 8 degrees) and further back than the one before it.
  std::vector<double> nodes = {0.0};
  const std::vector<double>& w0 = past_[0].weights;
  if (extrapolate && past_[0].node && w0.size() == weights.size()) {
    double d_sq = 0.0;
    for (size_t t = 0; t < weights.size(); ++t) d_sq += (weights[t] - w0[t]) * (weights[t] - w0[t]);
    for (size_t k = 1; k < past_.size() && d_sq > 0.0; ++k) {
      const std::vector<double>& wk = past_[k].weights;
      if (!past_[k].node || wk.size() != weights.size() || past_[k].motion.has_value() != anchored) break;
      double along = 0.0, off_sq = 0.0;
      for (size_t t = 0; t < weights.size(); ++t) along += (wk[t] - w0[t]) * (weights[t] - w0[t]);
      const double tk = along / d_sq;
      for (size_t t = 0; t < weights.size(); ++t) {
        const double off = wk[t] - w0[t] - tk * (weights[t] - w0[t]);
        off_sq += off * off;
      }
      // The spacing to the node before: this frame's step is at most twice the last frame's; further back,
      // steps vary by at most a factor of 2.
      const double spacing = nodes.back() - tk;  // > 0: further back
      const double last_spacing = k == 1 ? 1.0 : nodes[k - 2] - nodes[k - 1];
      const bool spaced =
          k == 1 ? 2.0 * spacing >= 1.0 : spacing <= 2.0 * last_spacing && 2.0 * spacing >= last_spacing;
      if (!(spacing > 0.0) || !spaced || off_sq > 0.02 * tk * tk * d_sq) break;
      nodes.push_back(tk);
    }
  }
  // The polynomial through the first `order` + 1 nodes, at t = 1, with this frame's held vertices.
  const std::optional<AnchorMotion> none;
  const auto predict = [&](size_t order, Eigen::VectorXd* out) {
    out->resize(3 * n);
    std::vector<double> lagrange(order + 1, 1.0);
    for (size_t i = 0; i <= order; ++i) {
      for (size_t j = 0; j <= order; ++j) {
        if (j != i) lagrange[i] *= (1.0 - nodes[j]) / (nodes[i] - nodes[j]);
      }
    }
    for (int v = 0; v < n; ++v) {
      Eigen::Vector3d local = Eigen::Vector3d::Zero();
      for (size_t k = 0; k <= order; ++k) {
        local += lagrange[k] * to_local(past_[k].positions.row(v).transpose(), anchored ? past_[k].motion : none);
      }
      out->segment<3>(3 * v) = anchored ? to_world(local) : local;
    }
    for (const auto& [v, p] : held) out->segment<3>(3 * v) = p;
  };
  predict(nodes.size() - 1, &x);
  if (nodes.size() == 1) return;
  double best = energy(x);
  Eigen::VectorXd trial;
  for (size_t order = nodes.size() - 1; order-- > 0;) {
    predict(order, &trial);
    const double e = energy(trial);
    if (e < best) {
      best = e;
      x.swap(trial);
    }
  }
}

}  // namespace springblend::internal
