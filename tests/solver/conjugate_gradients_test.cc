// Preconditioned conjugate gradients on small systems with known answers.
#include "conjugate_gradients.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>

namespace springblend::internal {
namespace {

// The 1D Laplacian with Dirichlet ends plus a small diagonal: SPD, condition number ~ n^2.
Eigen::MatrixXd Laplacian(int n) {
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(n, n);
  for (int i = 0; i < n; ++i) {
    a(i, i) = 2.01;
    if (i > 0) a(i, i - 1) = a(i - 1, i) = -1.0;
  }
  return a;
}

TEST(ConjugateGradients, SolvesAnSpdSystemToItsKnownAnswer) {
  const int n = 50;
  const Eigen::MatrixXd a = Laplacian(n);
  const Eigen::VectorXd answer = Eigen::VectorXd::LinSpaced(n, -1.0, 2.0);
  const Eigen::VectorXd b = a * answer;
  ConjugateGradients cg(n);
  ConjugateGradientsOptions options;
  options.target_norm = 1e-12 * b.norm();
  options.max_iterations = 200;
  Eigen::VectorXd x(n);
  int iterations = 0;
  const auto status = cg.Solve([&](const Eigen::VectorXd& v, Eigen::VectorXd* out) { *out = a * v; },
                               [](const Eigen::VectorXd& r, Eigen::VectorXd* z) { *z = r; }, b, options, &x,
                               &iterations);
  EXPECT_EQ(status, ConjugateGradientsStatus::kConverged);
  EXPECT_LT((x - answer).lpNorm<Eigen::Infinity>(), 1e-9);
  EXPECT_LE(iterations, n + 1);  // exact arithmetic needs at most n
}

TEST(ConjugateGradients, AnExactPreconditionerConvergesInOneIteration) {
  const int n = 30;
  const Eigen::MatrixXd a = Laplacian(n);
  const Eigen::LLT<Eigen::MatrixXd> factor(a);
  const Eigen::VectorXd b = Eigen::VectorXd::Ones(n);
  ConjugateGradients cg(n);
  ConjugateGradientsOptions options;
  options.target_norm = 1e-10;
  Eigen::VectorXd x(n);
  int iterations = 0;
  cg.Solve([&](const Eigen::VectorXd& v, Eigen::VectorXd* out) { *out = a * v; },
           [&](const Eigen::VectorXd& r, Eigen::VectorXd* z) { *z = factor.solve(r); }, b, options, &x, &iterations);
  EXPECT_EQ(iterations, 1);
  EXPECT_LT((a * x - b).norm(), 1e-10);
}

TEST(ConjugateGradients, ReportsNegativeCurvatureAndTheDirectionThatMetIt) {
  Eigen::MatrixXd a = Eigen::MatrixXd::Identity(3, 3);
  a(2, 2) = -1.0;  // indefinite
  const Eigen::VectorXd b(Eigen::Vector3d(0.0, 0.0, 1.0));
  ConjugateGradients cg(3);
  Eigen::VectorXd x(3);
  int iterations = 0;
  const auto status = cg.Solve([&](const Eigen::VectorXd& v, Eigen::VectorXd* out) { *out = a * v; },
                               [](const Eigen::VectorXd& r, Eigen::VectorXd* z) { *z = r; }, b, {}, &x, &iterations);
  EXPECT_EQ(status, ConjugateGradientsStatus::kNegativeCurvature);
  const Eigen::VectorXd& d = cg.last_direction();
  EXPECT_LT(d.dot(a * d), 0.0);
}

TEST(ConjugateGradients, StopsAtTheIterationCap) {
  const int n = 100;
  const Eigen::MatrixXd a = Laplacian(n);
  ConjugateGradients cg(n);
  ConjugateGradientsOptions options;
  options.target_norm = 1e-14;
  options.max_iterations = 5;
  Eigen::VectorXd x(n);
  int iterations = 0;
  const auto status =
      cg.Solve([&](const Eigen::VectorXd& v, Eigen::VectorXd* out) { *out = a * v; },
               [](const Eigen::VectorXd& r, Eigen::VectorXd* z) { *z = r; }, Eigen::VectorXd::Ones(n), options, &x,
               &iterations);
  EXPECT_EQ(status, ConjugateGradientsStatus::kMaxIterations);
  EXPECT_EQ(iterations, 5);
}

}  // namespace
}  // namespace springblend::internal
