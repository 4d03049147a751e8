#include "conjugate_gradients.h"

#include <cmath>

namespace springblend::internal {

ConjugateGradients::ConjugateGradients(Eigen::Index size)
    : residual_(size), preconditioned_(size), direction_(size), product_(size) {}

ConjugateGradientsStatus ConjugateGradients::Solve(const Operator& a, const Operator& preconditioner,
                                                   const Eigen::VectorXd& b,
                                                   const ConjugateGradientsOptions& options, Eigen::VectorXd* x,
                                                   int* iterations) {
  x->setZero();
  residual_ = b;
  preconditioner(residual_, &preconditioned_);
  direction_ = preconditioned_;
  double rz = residual_.dot(preconditioned_);
  for (int it = 0; it < options.max_iterations; ++it) {
    a(direction_, &product_);
    ++*iterations;
    const double curvature = direction_.dot(product_);
    if (!(curvature > 0.0) || !std::isfinite(curvature)) return ConjugateGradientsStatus::kNegativeCurvature;
    const double alpha = rz / curvature;
    *x += alpha * direction_;
    residual_ -= alpha * product_;
    if (residual_.norm() <= options.target_norm || residual_.lpNorm<Eigen::Infinity>() <= options.floor) {
      return ConjugateGradientsStatus::kConverged;
    }
    preconditioner(residual_, &preconditioned_);
    const double rz_next = residual_.dot(preconditioned_);
    direction_ = preconditioned_ + (rz_next / rz) * direction_;
    rz = rz_next;
  }
  return ConjugateGradientsStatus::kMaxIterations;
}

}  // namespace springblend::internal
