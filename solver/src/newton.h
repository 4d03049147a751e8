// Inexact Newton (method.md section 4): each step solves H d = f by conjugate gradients preconditioned
// with a kept factorization (reused across iterations and frames, refactored when it stops paying off),
// with Eisenstat-Walker forcing terms, a step-length clamp and a backtracking line search on the energy.
// With reuse_factorization off it is plain Newton with a fresh factorization and a direct solve per step.
#pragma once

#include "conjugate_gradients.h"
#include "minimizer.h"

namespace springblend::internal {

class InexactNewton final : public Minimizer {
 public:
  explicit InexactNewton(const MinimizerOptions& options) : options_(options) {}
  void Minimize(const MinimizerProblem& problem, Eigen::VectorXd* x, MinimizerSummary* summary) override;
  void SetOptions(const MinimizerOptions& options) override { options_ = options; }
  MinimizerType type() const override { return MinimizerType::kInexactNewton; }
  void Reset() override {
    rung_ = 0;
    refactor_next_ = false;
  }

 private:
  // The Newton direction step_ from the forces at *x. False (with the summary's message) on failure.
  bool Direction(const MinimizerProblem& problem, const Eigen::VectorXd& x, double forcing,
                 MinimizerSummary* summary);
  // A fresh factorization (the ladder) and the Newton step with it, accurate to `forcing` (relative residual in
  // the factored system) where the factor is kept as a preconditioner, exact otherwise.
  bool FactorizeAndSolve(const MinimizerProblem& problem, const Eigen::VectorXd& x, double forcing,
                         MinimizerSummary* summary);
  ConjugateGradientsStatus ConjugateGradientStep(const MinimizerProblem& problem, double forcing,
                                                 MinimizerSummary* summary);
  // Newton-CG preconditioned by the Laplacian: true Hessian, then projected; a truncated (but descending)
  // CG step is taken as it is. False when neither gives a direction.
  bool LaplacianDirection(const MinimizerProblem& problem, const Eigen::VectorXd& x, double forcing,
                          MinimizerSummary* summary);
  Curvature CurvatureAt(double negative_scale) const {
    return {negative_scale, options_.hessian == HessianChoice::kAbsolute};
  }

  MinimizerOptions options_;
  // About the factorization kept in the linear system.
  size_t rung_ = 0;             // the ladder rung that succeeded last
  bool refactor_next_ = false;  // the last conjugate gradients cost too much: refactor at the next step
  std::vector<double> values_;  // the assembled Hessian
  Eigen::VectorXd step_, trial_;
  std::unique_ptr<ConjugateGradients> cg_;
  Eigen::VectorXd negative_direction_;
  bool has_negative_direction_ = false;
};

}  // namespace springblend::internal
