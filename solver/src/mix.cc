// The mixing models of mix.h: the superposed prediction and its rest lengths.
#include "mix.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cctype>
#include <string>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "frame_conditions.h"
#include "springblend/error.h"
#include "rig_internals.h"
#include "target_paths.h"

namespace springblend::internal {

std::vector<char> LinearTargets(const Rig& rig, const SolveOptions& options) {
  std::vector<char> linear(rig.num_targets(), 0);
  const auto lower = [](std::string s) {
    std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
    return s;
  };
  const bool given = options.linear_targets.has_value();
  for (const std::string& name : given ? *options.linear_targets : kDefaultCorrectives) {
    bool found = false;
    for (int t = 0; t < rig.num_targets(); ++t) {
      if (lower(rig.target_names()[t]) == lower(name)) linear[t] = 1, found = true;
    }
    if (!found && given) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("solve option linear_targets names '{}', which is no target of the rig ({})", name,
                              fmt::join(rig.target_names(), ", ")));
    }
  }
  return linear;
}

}  // namespace springblend::internal

namespace springblend {

void ValidateOptions(const Rig& rig, const SolveOptions& options) {
  options.Validate();
  internal::LinearTargets(rig, options);
}

}  // namespace springblend

namespace springblend::internal {

bool IsSuperposedMix(const SolveOptions& options, const std::vector<char>& linear, const std::vector<double>& weights) {
  if (options.mix != MixModel::kSuperposed) return false;
  int moved = 0;
  bool any_linear = false;
  for (size_t t = 0; t < weights.size(); ++t) {
    if (weights[t] == 0.0) continue;
    ++moved;
    any_linear = any_linear || (t < linear.size() && linear[t]);
  }
  return moved >= 2 || any_linear;
}

namespace {

// Each target's share of its own physical correction and strain in this frame: 0 for a linear target; where a
// sculpted combination it drives is on, 1 - its weight (its product of drivers' weights, at most 1) for each such
// combination: at every driver 1 the artist's sculpt is the whole answer, as in the paper's blend.
std::vector<double> PhysicalFactors(const Rig& rig, const std::vector<double>& weights, const std::vector<char>& linear) {
  std::vector<double> factor(weights.size(), 1.0);
  for (size_t t = 0; t < factor.size() && t < linear.size(); ++t) {
    if (linear[t]) factor[t] = 0.0;
  }
  for (const auto& combination : rig.internals().controls.combinations) {
    double product = 1.0;
    for (int d : combination.drivers) product *= d < static_cast<int>(weights.size()) ? weights[d] : 0.0;
    const double fade = 1.0 - std::min(1.0, std::abs(product));
    for (int d : combination.drivers) {
      if (d < static_cast<int>(factor.size())) factor[d] *= fade;
    }
  }
  return factor;
}

// The physical targets' corrections at their weights (each scaled by its factor; the anchor's frame), averaged
// per vertex with their magnitudes as weights, sum c|c| / sum |c|: a target's own correction where it alone
// corrects a vertex, never longer than the longest where several do. One target: its correction exactly.
// #vertices by 3. (Summed, as the linear blend sums deltas, the corrections of a captured face's 20-40
// expressions point the same way at the lips, each restoring its own target's arc, and added up to 2.3 % of the
// diagonal from the linear blend where every expression's own was under 0.7 %. Summed but capped per vertex at
// the longest, 1.26 % on the same frames, and the lips pressed closer than the springs' floor, so that frames the
// average leaves at rest took 7-10 Newton iterations.)
Eigen::MatrixXd AveragedCorrection(const Rig& rig, const std::vector<double>& weights,
                                   const std::vector<double>& factors, int n) {
  const std::vector<TargetPath>& paths = rig.internals().paths;
  Eigen::MatrixXd weighted = Eigen::MatrixXd::Zero(n, 3), c;
  Eigen::VectorXd magnitude = Eigen::VectorXd::Zero(n);
  int count = 0;
  for (size_t t = 0; t < paths.size() && t < weights.size(); ++t) {
    if (paths[t].empty() || weights[t] == 0.0 || factors[t] == 0.0) continue;
    EvaluatePath(paths[t], weights[t], &c);
    c *= factors[t];
    if (count++ == 0) {
      weighted.swap(c);  // a sole target's correction stays exactly itself
      continue;
    }
    if (count == 2) magnitude = weighted.rowwise().norm(), weighted.array().colwise() *= magnitude.array();
    const Eigen::VectorXd norm = c.rowwise().norm();
    weighted.array() += c.array().colwise() * norm.array();
    magnitude += norm;
  }
  if (count < 2) return weighted;
  for (int v = 0; v < n; ++v) {
    if (magnitude[v] > 0.0) weighted.row(v) /= magnitude[v];
  }
  return weighted;
}

// Target t alone at its weight in this frame: its sculpted shapes that change lengths, with their weights (its
// in-betweens blend in as the frame's would).
std::vector<std::pair<int, double>> LengthShapesAlone(const Rig& rig, const std::vector<double>& weights, int t) {
  std::vector<double> single(weights.size(), 0.0);
  single[t] = weights[t];
  const std::vector<double> shape_weights = rig.ShapeWeights(single);
  std::vector<std::pair<int, double>> shapes;
  for (int s = 0; s < rig.num_shapes(); ++s) {
    if (shape_weights[s] != 0.0 && rig.target_changes_lengths(s)) shapes.emplace_back(s, shape_weights[s]);
  }
  return shapes;
}

// How much of the targets' residual strains a mix carries: 2 S_max / sum_t S_t - 1 clamped to [0, 1], S_t the
// size of target t's length changes at its weight (sum over springs of |w_t (r^t - r^0)|, times its factor). 1 where
// one target alone changes lengths (the paper's frame: its strains exactly), falling as others join, 0 once the
// largest changes no more than all the others together.
double PrestressShare(const Rig& rig, const std::vector<double>& weights, const std::vector<double>& factors,
                      const std::vector<int>& moved) {
  if (moved.empty()) return 0.0;
  const int m = rig.num_springs();
  std::vector<double> size(moved.size(), 0.0);
  tbb::parallel_for(size_t{0}, moved.size(), [&](size_t i) {
    std::vector<double> change(m, 0.0);
    for (const auto& [s, w] : LengthShapesAlone(rig, weights, moved[i])) {
      const std::vector<double>& delta = rig.rest_length_delta(s);
      for (int q = 0; q < m; ++q) change[q] += w * delta[q];
    }
    double sum = 0.0;
    for (double c : change) sum += std::abs(c);
    size[i] = std::abs(factors[moved[i]]) * sum;
  });
  double total = 0.0, largest = 0.0;
  for (double s : size) total += s, largest = std::max(largest, s);
  if (!(total > 0.0)) return moved.size() == 1 ? 1.0 : 0.0;
  return std::clamp(2.0 * largest / total - 1.0, 0.0, 1.0);
}

}  // namespace

void Prediction(const Rig& rig, const std::vector<double>& weights, const std::vector<char>& linear, bool use_paths,
                Eigen::VectorXd* y) {
  const std::vector<double> shape_weights = rig.ShapeWeights(weights);
  const Points blend = LinearBlendShapes(rig, shape_weights);
  const int n = static_cast<int>(blend.rows());
  y->resize(3 * n);
  for (int v = 0; v < n; ++v) y->segment<3>(3 * v) = blend.row(v).transpose();
  const FrameConditions conditions = ConditionsOf(rig, shape_weights, blend, {});
  if (use_paths) {
    const Eigen::MatrixXd correction = AveragedCorrection(rig, weights, PhysicalFactors(rig, weights, linear), n);
    const Eigen::Matrix3d rotation =
        conditions.motion ? conditions.motion->rotation.toRotationMatrix() : Eigen::Matrix3d::Identity();
    for (int v = 0; v < n; ++v) y->segment<3>(3 * v) += rotation * correction.row(v).transpose();
  }
  for (const auto& [v, p] : conditions.held) y->segment<3>(3 * v) = p;
}

double SuperposedRestLengths(const Rig& rig, const std::vector<double>& weights, const std::vector<char>& linear,
                             bool use_paths, const Eigen::VectorXd& y, std::vector<double>* rest_lengths) {
  const int m = rig.num_springs();
  const std::vector<int>& a = rig.spring_a();
  const std::vector<int>& b = rig.spring_b();
  const std::vector<double>& r0 = rig.rest_lengths();
  const double floor = rig.options().min_rest_length_fraction * rig.summary().mean_rest_length;
  // Each moved target alone at its weight: its sculpted shapes' weights (in-betweens blend in) and the
  // prediction of that single-target frame (its path's equilibrium, to the path's tolerance).
  struct Alone {
    std::vector<std::pair<int, double>> shapes;  // sculpted shape, weight (nonzero, changing lengths)
    Eigen::VectorXd x;
    double factor = 1.0;
  };
  auto length = [&](const Eigen::VectorXd& x, int q) { return (x.segment<3>(3 * a[q]) - x.segment<3>(3 * b[q])).norm(); };
  const std::vector<double> factors = PhysicalFactors(rig, weights, linear);
  std::vector<int> moved;
  for (size_t t = 0; t < weights.size(); ++t) {
    if (weights[t] != 0.0 && factors[t] != 0.0) moved.push_back(static_cast<int>(t));
  }
  const double share = PrestressShare(rig, weights, factors, moved);
  rest_lengths->resize(m);
  if (share == 0.0) {
    // No target dominates: the springs rest at the prediction, which is the answer (energy zero). The floor on
    // rest lengths (min_rest_length_fraction) keeps a blend of length changes from going to zero or below; a
    // length of y is one already, and held up to the floor it would push apart lips that y closes.
    double* out = rest_lengths->data();
    tbb::parallel_for(tbb::blocked_range<int>(0, m, 4096), [&](const tbb::blocked_range<int>& range) {
      for (int q = range.begin(); q != range.end(); ++q) out[q] = length(y, q);
    });
    return share;
  }
  // The targets' strains summed per spring in target order, a few targets' predictions at a time (their memory
  // bounded: each is a copy of the vertices), the same sums whatever the grouping.
  constexpr size_t kGroup = 4;
  std::vector<double> weighted(m, 0.0), magnitude(m, 0.0);
  for (size_t first = 0; first < moved.size(); first += kGroup) {
    std::vector<Alone> alone(std::min(kGroup, moved.size() - first));
    tbb::parallel_for(size_t{0}, alone.size(), [&](size_t i) {
      const int t = moved[first + i];
      alone[i].shapes = LengthShapesAlone(rig, weights, t);
      std::vector<double> single(weights.size(), 0.0);
      single[t] = weights[t];
      Prediction(rig, single, linear, use_paths, &alone[i].x);
      alone[i].factor = factors[t];
    });
    tbb::parallel_for(tbb::blocked_range<int>(0, m, 4096), [&](const tbb::blocked_range<int>& range) {
      for (int q = range.begin(); q != range.end(); ++q) {
        // Each target's residual strain here: its own blended rest length (as BlendRestLengths gives it, clamped)
        // less its length at its own prediction.
        for (const Alone& t : alone) {
          double own = r0[q];
          for (const auto& [s, w] : t.shapes) own += w * rig.rest_length_delta(s)[q];
          const double strain = share * t.factor * (std::max(own, floor) - length(t.x, q));
          weighted[q] += strain * std::abs(strain);
          magnitude[q] += std::abs(strain);
        }
      }
    });
  }
  // Averaged with their magnitudes as weights, sum e|e| / sum |e|: one target's strain exactly where it alone
  // strains the spring, never more than the largest where several do.
  double* out = rest_lengths->data();
  tbb::parallel_for(tbb::blocked_range<int>(0, m, 4096), [&](const tbb::blocked_range<int>& range) {
    for (int q = range.begin(); q != range.end(); ++q) {
      const double strain = magnitude[q] > 0.0 ? weighted[q] / magnitude[q] : 0.0;
      const double here = length(y, q);
      out[q] = std::max(here + strain, std::min(here, floor));  // never floored above y's own length
    }
  });
  return share;
}

}  // namespace springblend::internal
