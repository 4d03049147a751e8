// Preconditioned conjugate gradients for A x = b with A symmetric and (hopefully) positive definite, both
// A and the preconditioner given as products. Stops at a relative residual, an absolute floor, negative
// curvature, or an iteration cap.
#pragma once

#include <Eigen/Core>
#include <functional>

namespace springblend::internal {

struct ConjugateGradientsOptions {
  double target_norm = 0.0;     // stop when |r|_2 <= this
  double floor = 0.0;           // ... or when |r|_inf <= this
  int max_iterations = 40;
};

enum class ConjugateGradientsStatus {
  kConverged,
  kNegativeCurvature,  // d^T A d <= 0 (or not finite) for a search direction d
  kMaxIterations,
};

class ConjugateGradients {
 public:
  using Operator = std::function<void(const Eigen::VectorXd& in, Eigen::VectorXd* out)>;

  explicit ConjugateGradients(Eigen::Index size);
  // Solves from x = 0. *iterations counts products with A.
  ConjugateGradientsStatus Solve(const Operator& a, const Operator& preconditioner, const Eigen::VectorXd& b,
                                 const ConjugateGradientsOptions& options, Eigen::VectorXd* x, int* iterations);
  // The search direction along which the last Solve met negative curvature.
  const Eigen::VectorXd& last_direction() const { return direction_; }

 private:
  Eigen::VectorXd residual_, preconditioned_, direction_, product_;
};

}  // namespace springblend::internal
