// The solves along one target's path (path_sweep.cc): its samples, by continuation from the branch's last ones,
// their exact tangents and the midpoint checks, for the build of its path (target_paths.cc).
#pragma once

#include <Eigen/Core>

#include <cmath>
#include <deque>
#include <functional>
#include <memory>
#include <vector>

#include "conjugate_gradients.h"
#include "frame_conditions.h"
#include "linear_system.h"
#include "minimizer.h"
#include "spring_system.h"
#include "springblend/rig.h"
#include "target_paths.h"

namespace springblend::internal {

struct Sample {
  double alpha = 0.0;
  Eigen::MatrixXd correction;  // anchor's frame
  Eigen::MatrixXd tangent;     // its exact derivative in alpha, or empty
  double energy = 0.0;         // infinite when a tentative solve failed
  bool converged = false;
  bool jumped = false;         // its solve went over a fold: far from a start extrapolated along the branch
  bool fold_before = false;    // (assembled path) the interval below it is a fold
  bool two_words = false;      // stored in one word, it would start out of balance at its own alpha
};

// The last samples of the branch a sweep follows, newest first: the polynomial through them, in the
// corrections (which vary smoothly where the linear blend carries most of the motion), predicts the next.
class Continuation {
 public:
  static constexpr size_t kOrder = 2;  // at most quadratic
  void Reset() { past_.clear(); }
  void Add(double alpha, const Points& correction, const Eigen::MatrixXd& tangent) {
    // An empty tangent stays empty (0 x 3): Points has three columns, an empty MatrixXd none.
    Points t = tangent.size() > 0 ? Points(tangent) : Points(0, 3);
    past_.push_front({alpha, correction, std::move(t)});
    if (past_.size() > kOrder + 1) past_.pop_back();
  }
  void Add(const Sample& sample) {
    if (sample.converged) Add(sample.alpha, sample.correction, sample.tangent);
  }
  // The predictions at alpha of orders 0 up to what the samples allow (none without samples). A sample
  // joins while the spacing stays within a factor 2 of the step, as the continuation's halvings keep it.
  std::vector<Points> Candidates(double alpha) const {
    std::vector<Points> out;
    size_t count = 0;
    double last = alpha;
    for (const Past& past : past_) {
      const double a = past.alpha;
      const double spacing = std::abs(last - a);
      if (count > 0 && (spacing == 0.0 || spacing > 2.5 * std::abs(alpha - past_[0].alpha))) break;
      last = a;
      ++count;
    }
    for (size_t order = 0; order < count; ++order) {
      Points p = Points::Zero(past_[0].correction.rows(), 3);
      for (size_t i = 0; i <= order; ++i) {
        double l = 1.0;
        for (size_t j = 0; j <= order; ++j) {
          if (j != i) l *= (alpha - past_[j].alpha) / (past_[i].alpha - past_[j].alpha);
        }
        p += l * past_[i].correction;
      }
      out.push_back(std::move(p));
    }
    // With exact tangents: the cubic Hermite through the last two samples (their values and tangents),
    // extrapolated, else the last sample's tangent line. Last, so that it is the one a jump is measured from.
    if (count >= 1 && past_[0].tangent.size() > 0) {
      const Past& p0 = past_[0];
      if (count >= 2 && past_[1].tangent.size() > 0) {
        const Past& p1 = past_[1];
        const double h = p0.alpha - p1.alpha, t = (alpha - p1.alpha) / h;
        const double t2 = t * t, t3 = t2 * t;
        out.push_back((2 * t3 - 3 * t2 + 1) * p1.correction + (h * (t3 - 2 * t2 + t)) * p1.tangent +
                      (-2 * t3 + 3 * t2) * p0.correction + (h * (t3 - t2)) * p0.tangent);
      } else {
        out.push_back(p0.correction + (alpha - p0.alpha) * p0.tangent);
      }
    }
    return out;
  }

 private:
  struct Past {
    double alpha;
    Points correction, tangent;
  };
  std::deque<Past> past_;
};

// The solves along one target's path, sharing one spring system, linear system and minimizer (whose kept
// factorization preconditions the next sample while it stays close).
class PathSolver {
 public:
  PathSolver(const Rig& rig, int target, double tolerance, const std::function<bool()>* stop);

  std::vector<double> Weights(double alpha) const;  // the target alone at alpha

  // The target alone at alpha: its weights, linear blend and conditions, with the springs' rest lengths set.
  struct Setup {
    std::vector<double> weights;
    Points linear;
    FrameConditions conditions;
  };
  Setup SetUp(double alpha);
  // The sculpted shape of a knot (alpha 0, an in-between's weight, 1), a zero correction where it is in balance.
  Sample End(double alpha);
  // The exact tangent at a sample given by its correction (anchor's frame).
  Eigen::MatrixXd TangentOf(double alpha, const Eigen::MatrixXd& correction);
  // The exact tangent of a sample's correction at its equilibrium x; empty where it has none.
  Eigen::MatrixXd Tangent(double alpha, Eigen::VectorXd x);

  int solves = 0;  // equilibria solved (tentative ones that failed not counted)
  int newton_iterations = 0;
  int tangent_cg_iterations = 0;
  int local_checks = 0;  // midpoint checks finished locally

  // Solves alpha * target coming from `from`, halving the step where Newton does not converge.
  void Refined(double from, double alpha, Continuation& continuation, std::vector<Sample>* out, int depth = 0);
  // Solves the target at alpha from the predictor's start, or from `correction` (anchor's frame) when given.
  Sample Solve(double alpha, Continuation* continuation, const Eigen::MatrixXd* correction, bool tentative = false,
               int max_iterations = 0, const TargetPath* around = nullptr);
  // A midpoint check's start finished as a path frame is; false where that gave up.
  bool FinishLocally(double alpha, const FrameConditions& conditions, const TargetPath& around, Eigen::VectorXd* x,
                     MinimizerSummary* summary);
  // Whether a sample's correction (anchor's frame) needs two words (PathField).
  bool NeedsTwoWords(double alpha, const Points& correction);

 private:
  const Rig& rig_;
  int target_;
  const std::function<bool()>* stop_;
  MinimizerOptions sample_options_;
  SpringSystem springs_;
  LinearSystem linear_;
  std::unique_ptr<Minimizer> minimizer_;
  std::unique_ptr<ConjugateGradients> cg_;
  std::vector<char> held_;
};

}  // namespace springblend::internal
