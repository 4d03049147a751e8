// The spring system: forces are minus the energy's gradient, the assembled Hessian is its derivative and
// equals the matrix-free product, held coordinates are identity rows.
#include "spring_system.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <random>

namespace springblend::internal {
namespace {

// A small random tetrahedral cluster of springs.
struct Cluster {
  int n = 6;
  std::vector<int> a, b, offsets, incident;
  std::vector<SpringKind> kinds;
  HessianPattern pattern;
  Eigen::VectorXd x;
  std::vector<double> rest;
  Cluster() {
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    for (int i = 0; i < n; ++i) {
      for (int j = i + 1; j < n; ++j) {
        if ((i + j) % 4 == 3) continue;
        a.push_back(i), b.push_back(j), kinds.push_back(SpringKind::kStructure);
      }
    }
    offsets.assign(n + 1, 0);
    for (size_t q = 0; q < a.size(); ++q) ++offsets[a[q] + 1], ++offsets[b[q] + 1];
    for (int v = 0; v < n; ++v) offsets[v + 1] += offsets[v];
    incident.resize(2 * a.size());
    std::vector<int> fill(offsets.begin(), offsets.end() - 1);
    for (size_t q = 0; q < a.size(); ++q) {
      incident[fill[a[q]]++] = static_cast<int>(q);
      incident[fill[b[q]]++] = static_cast<int>(q);
    }
    pattern = HessianPattern::Build(n, a, b);
    x.resize(3 * n);
    for (int d = 0; d < 3 * n; ++d) x[d] = u(rng);
    // Some springs stretched, some compressed (negative transverse stiffness).
    for (size_t q = 0; q < a.size(); ++q) {
      const double l = (x.segment<3>(3 * a[q]) - x.segment<3>(3 * b[q])).norm();
      rest.push_back(l * (q % 2 == 0 ? 0.7 : 1.4));
    }
  }
  SpringTopology Topology() const {
    SpringTopology t;
    t.vertices = n;
    t.a = a, t.b = b, t.vertex_spring_offsets = offsets, t.vertex_springs = incident;
    t.pattern = &pattern;
    return t;
  }
  Eigen::MatrixXd Dense(const std::vector<double>& values) const {
    const int size = 3 * n;
    Eigen::MatrixXd m = Eigen::MatrixXd::Zero(size, size);
    for (int j = 0; j < size; ++j) {
      for (int k = pattern.matrix.column_starts[j]; k < pattern.matrix.column_starts[j + 1]; ++k) {
        m(pattern.matrix.row_indices[k], j) = m(j, pattern.matrix.row_indices[k]) = values[k];
      }
    }
    return m;
  }
};

TEST(SpringSystem, ForcesAreMinusTheGradientAndTheHessianItsDerivative) {
  const Cluster c;
  SpringSystem springs(c.Topology());
  springs.SetRestLengths(c.rest, c.kinds, {1.0, 1.0, 1.0}, 0.01);
  const std::vector<char> none(3 * c.n, 0);
  std::vector<double> values(c.pattern.matrix.row_indices.size());
  springs.Assemble(c.x, none, {1.0, false}, 0.0, &values);
  const Eigen::VectorXd force = springs.force();
  const Eigen::MatrixXd hessian = c.Dense(values);
  const double h = 1e-6;
  for (int d = 0; d < 3 * c.n; ++d) {
    Eigen::VectorXd plus = c.x, minus = c.x;
    plus[d] += h, minus[d] -= h;
    const double gradient = (springs.Energy(plus) - springs.Energy(minus)) / (2 * h);
    EXPECT_NEAR(-force[d], gradient, 1e-6);
    springs.Evaluate(plus, none, {1.0, false});
    const Eigen::VectorXd f_plus = springs.force();
    springs.Evaluate(minus, none, {1.0, false});
    const Eigen::VectorXd column = -(f_plus - springs.force()) / (2 * h);
    EXPECT_LT((column - hessian.col(d)).lpNorm<Eigen::Infinity>(), 1e-5) << "column " << d;
  }
}

TEST(SpringSystem, TheMatrixFreeProductEqualsTheAssembledMatrixWithHeldCoordinates) {
  const Cluster c;
  SpringSystem springs(c.Topology());
  springs.SetRestLengths(c.rest, c.kinds, {1.0, 1.0, 1.0}, 0.01);
  std::vector<char> held(3 * c.n, 0);
  held[0] = held[1] = held[2] = held[7] = 1;
  std::vector<double> values(c.pattern.matrix.row_indices.size());
  const double shift = 0.25;
  springs.Assemble(c.x, held, {0.0, false}, shift, &values);  // projected
  const Eigen::MatrixXd m = c.Dense(values);
  Eigen::VectorXd v = Eigen::VectorXd::LinSpaced(3 * c.n, -1.0, 1.0);
  for (int d = 0; d < 3 * c.n; ++d) {
    if (held[d]) v[d] = 0.0;
  }
  Eigen::VectorXd product(3 * c.n);
  springs.HessianProduct(v, held, shift, &product);
  EXPECT_LT((product - m * v).lpNorm<Eigen::Infinity>(), 1e-12);
  for (int d = 0; d < 3 * c.n; ++d) {
    if (!held[d]) continue;
    EXPECT_EQ(m(d, d), 1.0);
    EXPECT_EQ(springs.force()[d], 0.0);
  }
  // Projected blocks are positive semi-definite: the free part of the matrix minus the shift has no
  // negative eigenvalue.
  EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(m).eigenvalues().minCoeff(), 0.0);
}

// The product of several columns at once (the path span step's) equals the one-column product per column,
// with the true Hessian (compressed springs' negative transverse stiffness kept) and held coordinates.
TEST(SpringSystem, TheManyColumnProductEqualsTheOneColumnProductPerColumn) {
  const Cluster c;
  SpringSystem springs(c.Topology());
  springs.SetRestLengths(c.rest, c.kinds, {1.0, 1.0, 1.0}, 0.01);
  std::vector<char> held(3 * c.n, 0);
  held[3] = held[4] = held[11] = 1;
  springs.Evaluate(c.x, held, Curvature{}, true);
  const int k = 5;
  SpringSystem::Columns v(3 * c.n, k);
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (Eigen::Index d = 0; d < v.rows(); ++d) {
    for (int j = 0; j < k; ++j) v(d, j) = u(rng);
  }
  const double shift = 0.125;
  SpringSystem::Columns products;
  springs.HessianProducts(v, held, shift, &products);
  ASSERT_EQ(products.rows(), v.rows());
  ASSERT_EQ(products.cols(), k);
  Eigen::VectorXd product(3 * c.n);
  for (int j = 0; j < k; ++j) {
    springs.HessianProduct(v.col(j), held, shift, &product);
    EXPECT_LT((products.col(j) - product).lpNorm<Eigen::Infinity>(), 1e-12) << "column " << j;
  }
  for (int d = 0; d < 3 * c.n; ++d) {
    if (held[d]) {
      EXPECT_EQ(products.row(d).lpNorm<Eigen::Infinity>(), 0.0);
    }
  }
}

}  // namespace
}  // namespace springblend::internal
