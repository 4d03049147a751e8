// L-BFGS on the spring energy with the scalar Laplacian as its initial inverse Hessian (Liu, Bouaziz and
// Kavan 2017, "Quasi-Newton methods for real-time simulation of hyperelastic materials"): each iteration is
// one force pass, one n x n solve with three right-hand sides, the two-loop recursion and a backtracking line
// search; no 3n x 3n factorization. Pairs with y.s <= 0 (compressed springs) are skipped, not fatal. On a
// stall, or when its iteration budget is spent, the frame is finished by inexact Newton from where it got.
#pragma once

#include <deque>

#include "minimizer.h"
#include "newton.h"

namespace springblend::internal {

class Lbfgs final : public Minimizer {
 public:
  explicit Lbfgs(const MinimizerOptions& options) : options_(options), newton_(options) {}
  void Minimize(const MinimizerProblem& problem, Eigen::VectorXd* x, MinimizerSummary* summary) override;
  void SetOptions(const MinimizerOptions& options) override {
    options_ = options;
    newton_.SetOptions(options);
  }
  MinimizerType type() const override { return MinimizerType::kLbfgs; }
  void Reset() override { newton_.Reset(); }

 private:
  // d = -H g by the two-loop recursion over the kept pairs, with the Laplacian as H_0.
  void Direction(const MinimizerProblem& problem, const Eigen::VectorXd& gradient, Eigen::VectorXd* direction);

  struct Pair {
    Eigen::VectorXd s, y;
    double rho;
  };
  MinimizerOptions options_;
  InexactNewton newton_;
  std::deque<Pair> pairs_;  // newest last
  Eigen::VectorXd q_, z_;
  std::vector<double> alpha_;
};

}  // namespace springblend::internal
