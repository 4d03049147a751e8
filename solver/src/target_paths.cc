#include "target_paths.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>

#include "frame_conditions.h"
#include "minimizer.h"
#include "predictor.h"
#include "rig_internals.h"
#include "rigid.h"

namespace springblend::internal {

namespace {

constexpr int kMaxHalvings = 3;

// The solves along one target's path, sharing one spring system, linear system and minimizer.
class PathSolver {
 public:
  PathSolver(const Rig& rig, int target)
      : rig_(rig),
        target_(target),
        springs_(TopologyOf(rig)),
        linear_(rig.internals().pattern->matrix, *rig.internals().cholesky, rig.options().linear_solver),
        minimizer_(Minimizer::Create(MinimizerOptions{})),
        held_(3 * static_cast<size_t>(rig.num_vertices()), 0) {
    springs_.set_length_scale(rig.summary().mean_rest_length);
  }

  struct Sample {
    Eigen::MatrixXf correction;  // in the anchor's frame
    double energy = 0.0;
  };
  // Solves alpha * target coming from `from` (the previous sample): where the continuation step is too long
  // for Newton to converge, it is halved (up to three times) and the path followed through the midpoints.
  Sample Refined(double from, double alpha, Predictor& predictor, TargetPathsReport& report, int depth = 0) {
    Predictor before = predictor;
    Sample sample = Solve(alpha, predictor, report, depth < kMaxHalvings);
    if (std::isfinite(sample.energy) || depth >= kMaxHalvings) return sample;
    predictor = std::move(before);
    const double middle = 0.5 * (from + alpha);
    Refined(from, middle, predictor, report, depth + 1);
    return Refined(middle, alpha, predictor, report, depth + 1);
  }

  // Solves alpha * target from the predictor's start. A tentative solve that fails is not counted.
  Sample Solve(double alpha, Predictor& predictor, TargetPathsReport& report, bool tentative = false) {
    const int n = rig_.num_vertices();
    std::vector<double> weights(rig_.num_shapes(), 0.0);
    weights[target_] = alpha;
    Points linear = rig_.shape(0);
    if (alpha != 0.0) linear += alpha * (rig_.shape(target_ + 1) - rig_.shape(0));
    std::vector<double> rest_lengths;
    BlendRestLengths(rig_, weights, &rest_lengths);
    springs_.SetRestLengths(std::move(rest_lengths), rig_.spring_kind(), KindStiffness(rig_.options()),
                            StiffnessFloor(rig_));
    const FrameConditions conditions = ConditionsOf(rig_, weights, linear, {});
    Eigen::VectorXd x;
    predictor.Predict(linear, conditions.motion, rig_.anchor_centroid(), weights, conditions.held, true,
                      [&](const Eigen::VectorXd& y) { return springs_.Energy(y); }, &x);
    MinimizerSummary summary;
    if (HoldConditions(rig_, conditions, &x, &held_)) {
      MinimizerProblem problem;
      problem.springs = &springs_;
      problem.linear = &linear_;
      problem.held = &held_;
      problem.diagonal_shift = conditions.diagonal_shift;
      problem.diagonal = rig_.summary().bounding_box_diagonal;
      problem.mean_rest_length = rig_.summary().mean_rest_length;
      MinimizerTiming timing;
      problem.timing = &timing;
      minimizer_->Minimize(problem, &x, &summary);
    }
    const bool converged = summary.termination == MinimizerTermination::kConverged;
    report.newton_iterations += summary.iterations;
    if (!converged && tentative) return {Eigen::MatrixXf(), std::numeric_limits<double>::infinity()};
    ++report.samples;
    if (!converged) ++report.unconverged;
    Points solved(n, 3);
    for (int v = 0; v < n; ++v) solved.row(v) = x.segment<3>(3 * v).transpose();
    if (conditions.mode == BoundaryMode::kFloating) {
      AlignRigidly(linear.topRows(rig_.num_surface_vertices()), &solved);
    }
    if (!solved.allFinite()) solved = linear;  // a broken sample only costs its frames a worse start
    predictor.Add(solved, conditions.motion, weights, converged);
    Points correction = solved - linear;
    if (conditions.motion) correction = correction * conditions.motion->rotation.toRotationMatrix();  // R^T per row
    return {correction.cast<float>(), converged ? summary.energy : std::numeric_limits<double>::infinity()};
  }

 private:
  const Rig& rig_;
  int target_;
  SpringSystem springs_;
  LinearSystem linear_;
  std::unique_ptr<Minimizer> minimizer_;
  std::vector<char> held_;
};

}  // namespace

std::vector<TargetPath> BuildTargetPaths(const Rig& rig, int intervals, double extension, TargetPathsReport* report) {
  const auto start = std::chrono::steady_clock::now();
  const int targets = rig.num_shapes();
  std::vector<TargetPath> paths(targets);
  std::vector<TargetPathsReport> reports(targets);
  const double step = 1.0 / intervals;
  const int below = static_cast<int>(std::ceil(extension * intervals - 1e-9));
  const int above = intervals + below;
  tbb::parallel_for(0, targets, [&](int t) {
    if (!rig.target_changes_lengths(t)) return;
    PathSolver solver(rig, t);
    TargetPath& path = paths[t];
    path.step = step;
    path.first = -below;
    // The rest shape (alpha 0) and the target (alpha 1) are both equilibria of zero energy. Follow the path
    // up from the rest shape and down from the target, and keep at each alpha the equilibrium of lower
    // energy, so both ends are reproduced exactly and the choice between branches depends on the alpha
    // alone. Beyond [0, 1], continue from the nearer end.
    std::vector<PathSolver::Sample> up, down;
    Predictor from_rest;
    for (int k = 0; k <= intervals; ++k) up.push_back(solver.Refined((k - 1) * step, k * step, from_rest, reports[t]));
    std::vector<Eigen::MatrixXf> inside(intervals + 1);
    for (int k = 0; k <= intervals; ++k) inside[k] = up[k].correction;
    // When the way up ends on the target itself, the way down would retrace it: skip it.
    const double reached = up.back().correction.cwiseAbs().maxCoeff();
    if (!(reached <= 1e-6 * rig.summary().bounding_box_diagonal)) {
      Predictor from_target;
      for (int k = intervals; k >= 0; --k) {
        down.push_back(solver.Refined((k + 1) * step, k * step, from_target, reports[t]));
      }
      std::reverse(down.begin(), down.end());
      for (int k = 0; k <= intervals; ++k) {
        if (down[k].energy < up[k].energy) inside[k] = down[k].correction;
      }
    }
    const auto continue_from = [&](int end, int direction, int count, std::vector<Eigen::MatrixXf>* out) {
      // The predictor starts from the chosen end sample (a converged equilibrium).
      Predictor predictor;
      std::vector<double> weights(targets, 0.0);
      weights[t] = end * step;
      Points positions = rig.shape(0);
      if (end != 0) positions += weights[t] * (rig.shape(t + 1) - rig.shape(0));
      Points correction = inside[end].cast<double>();
      std::optional<AnchorMotion> motion;
      if (rig.boundary_mode() == BoundaryMode::kAnchored) {
        motion = BlendAnchorMotions(rig.internals().anchor_motions, weights);
        correction = correction * motion->rotation.toRotationMatrix().transpose();
      }
      predictor.Add(positions + correction, motion, weights, true);
      for (int k = 1; k <= count; ++k) {
        out->push_back(
            solver.Refined((end + direction * (k - 1)) * step, (end + direction * k) * step, predictor, reports[t])
                .correction);
      }
    };
    std::vector<Eigen::MatrixXf> beyond_one, before_zero;
    continue_from(intervals, +1, above - intervals, &beyond_one);
    continue_from(0, -1, below, &before_zero);
    path.corrections.assign(before_zero.rbegin(), before_zero.rend());
    path.corrections.insert(path.corrections.end(), inside.begin(), inside.end());
    path.corrections.insert(path.corrections.end(), beyond_one.begin(), beyond_one.end());
  });
  for (const TargetPathsReport& r : reports) {
    report->samples += r.samples;
    report->unconverged += r.unconverged;
    report->newton_iterations += r.newton_iterations;
  }
  report->ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return paths;
}

void AddPathCorrections(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                        const std::optional<AnchorMotion>& motion, Eigen::VectorXd* x) {
  const Eigen::Index n = x->size() / 3;
  Eigen::MatrixXd sum = Eigen::MatrixXd::Zero(n, 3);
  bool any = false;
  for (size_t t = 0; t < paths.size() && t < weights.size(); ++t) {
    const TargetPath& path = paths[t];
    if (path.empty() || weights[t] == 0.0) continue;
    const int samples = static_cast<int>(path.corrections.size());
    if (samples < 2) continue;
    // Position on the samples, held at the ends beyond them.
    double u = weights[t] / path.step - path.first;
    u = std::clamp(u, 0.0, static_cast<double>(samples - 1));
    const int k = std::min(static_cast<int>(std::floor(u)), samples - 2);
    const double s = u - k;
    // Catmull-Rom through samples k-1..k+2 (end tangents from one-sided differences).
    const Eigen::MatrixXd p1 = path.corrections[k].cast<double>();
    const Eigen::MatrixXd p2 = path.corrections[k + 1].cast<double>();
    const Eigen::MatrixXd p0 = k > 0 ? Eigen::MatrixXd(path.corrections[k - 1].cast<double>()) : Eigen::MatrixXd(2.0 * p1 - p2);
    const Eigen::MatrixXd p3 =
        k + 2 < samples ? Eigen::MatrixXd(path.corrections[k + 2].cast<double>()) : Eigen::MatrixXd(2.0 * p2 - p1);
    const double s2 = s * s, s3 = s2 * s;
    sum += 0.5 * (2.0 * p1 + (p2 - p0) * s + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * s2 +
                  (3.0 * p1 - p0 - 3.0 * p2 + p3) * s3);
    any = true;
  }
  if (!any) return;
  if (motion) sum = sum * motion->rotation.toRotationMatrix().transpose();  // R per row
  for (Eigen::Index v = 0; v < n; ++v) x->segment<3>(3 * v) += sum.row(v).transpose();
}

}  // namespace springblend::internal
