// The linear system with and without held coordinates, over every sparse Cholesky backend.
#include "linear_system.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <memory>
#include <thread>
#include <utility>

#include "hessian_pattern.h"

namespace springblend {
// Readable in ctest's output (gtest prints an enum class without PrintTo as raw bytes).
static void PrintTo(LinearSolverType type, std::ostream* os) { *os << ToString(type); }
}  // namespace springblend

namespace springblend::internal {
namespace {

// A chain of springs with extra diagonals: a small SPD matrix in the Hessian's 3n x 3n pattern.
struct Chain {
  Chain() = default;
  std::vector<int> a, b;
  HessianPattern pattern;
  std::vector<double> values;
  Eigen::MatrixXd dense;
  // The off-diagonal weights grow with the spring's index modulo `cycle`: a long chain stays diagonally
  // dominant (positive definite) with a small cycle.
  explicit Chain(int vertices, int cycle = 1 << 30) {
    for (int v = 0; v + 1 < vertices; ++v) a.push_back(v), b.push_back(v + 1);
    for (int v = 0; v + 2 < vertices; ++v) a.push_back(v), b.push_back(v + 2);
    Fill(vertices, cycle);
  }
  // A side x side grid with springs to the eight neighbours: its separators make supernodes of many columns
  // with rows below them, as a mesh's do.
  static Chain Grid(int side) {
    Chain grid;
    for (int i = 0; i < side; ++i) {
      for (int j = 0; j < side; ++j) {
        const int v = i * side + j;
        if (j + 1 < side) grid.a.push_back(v), grid.b.push_back(v + 1);
        if (i + 1 < side) grid.a.push_back(v), grid.b.push_back(v + side);
        if (i + 1 < side && j + 1 < side) grid.a.push_back(v), grid.b.push_back(v + side + 1);
        if (i + 1 < side && j > 0) grid.a.push_back(v), grid.b.push_back(v + side - 1);
      }
    }
    grid.Fill(side * side, 7);
    return grid;
  }
  void Fill(int vertices, int cycle) {
    pattern = HessianPattern::Build(vertices, a, b);
    const int n = 3 * vertices;
    dense = Eigen::MatrixXd::Zero(n, n);
    for (int j = 0; j < n; ++j) dense(j, j) = 8.0 + 0.1 * j;
    for (size_t q = 0; q < a.size(); ++q) {
      for (int c = 0; c < 3; ++c) {
        const double w = -1.0 - 0.05 * static_cast<double>(static_cast<int>(q) % cycle) - 0.2 * c;
        dense(3 * a[q] + c, 3 * b[q] + c) = dense(3 * b[q] + c, 3 * a[q] + c) = w;
      }
    }
    // Diagonally dominant: positive definite whatever the neighbours.
    for (int j = 0; j < n; ++j) dense(j, j) += dense.row(j).cwiseAbs().sum() - std::abs(dense(j, j));
    values.assign(pattern.matrix.row_indices.size(), 0.0);
    for (int j = 0; j < n; ++j) {
      for (int k = pattern.matrix.column_starts[j]; k < pattern.matrix.column_starts[j + 1]; ++k) {
        values[k] = dense(pattern.matrix.row_indices[k], j);
      }
    }
  }
  // The values with identity rows and columns for held coordinates.
  std::vector<double> Held(const std::vector<char>& held) const {
    std::vector<double> out = values;
    for (int j = 0; j < pattern.matrix.n; ++j) {
      for (int k = pattern.matrix.column_starts[j]; k < pattern.matrix.column_starts[j + 1]; ++k) {
        const int i = pattern.matrix.row_indices[k];
        if (held[i] || held[j]) out[k] = i == j ? 1.0 : 0.0;
      }
    }
    return out;
  }
};

// `count` held coordinates of n, every stride-th modulo n.
std::vector<char> HeldEvery(int n, int count, int stride) {
  std::vector<char> held(n, 0);
  for (int d = 0; d < count; ++d) held[(stride * d) % n] = 1;
  return held;
}

// v with its held coordinates zeroed.
Eigen::VectorXd FreeOnly(Eigen::VectorXd v, const std::vector<char>& held) {
  for (Eigen::Index d = 0; d < v.size(); ++d) {
    if (held[d]) v[d] = 0.0;
  }
  return v;
}

// A 14 x 14 grid's linear system on a backend: the factor has wide supernodes with rows below them.
struct GridSystem {
  explicit GridSystem(LinearSolverType type) : grid(Chain::Grid(14)), analyzed(SparseCholesky::Create(type)) {
    analyzed->Analyze(grid.pattern.matrix);
    system = std::make_unique<LinearSystem>(grid.pattern.matrix, *analyzed, type);
  }
  Chain grid;
  std::unique_ptr<SparseCholesky> analyzed;
  std::unique_ptr<LinearSystem> system;
};

class LinearSystemTest : public ::testing::TestWithParam<LinearSolverType> {};

TEST_P(LinearSystemTest, SolvesTheFreeCoordinatesWithAFewOrManyHeld) {
  const Chain chain(20);
  const int n = chain.pattern.matrix.n;
  auto analyzed = SparseCholesky::Create(GetParam());
  analyzed->Analyze(chain.pattern.matrix);
  LinearSystem system(chain.pattern.matrix, *analyzed, GetParam());
  const Eigen::VectorXd rhs = Eigen::VectorXd::LinSpaced(n, 1.0, -2.0);
  for (const int held_count : {0, 3, 30}) {  // none, few (full system), many (reduced system)
    std::vector<char> held(n, 0);
    for (int d = 0; d < held_count; ++d) held[(7 * d) % n] = 1;
    std::vector<int> free;
    for (int d = 0; d < n; ++d) {
      if (!held[d]) free.push_back(d);
    }
    Eigen::VectorXd b = rhs;
    for (int d = 0; d < n; ++d) {
      if (held[d]) b[d] = 0.0;
    }
    system.Select(held);
    ASSERT_EQ(system.Factorize(chain.Held(held)), FactorStatus::kOk);
    Eigen::VectorXd x(n);
    system.Solve(b, held, &x);
    // The reference: the dense system restricted to the free coordinates.
    const auto k = static_cast<Eigen::Index>(free.size());
    Eigen::MatrixXd a_ff(k, k);
    Eigen::VectorXd b_f(k);
    for (Eigen::Index i = 0; i < k; ++i) {
      b_f[i] = b[free[i]];
      for (Eigen::Index j = 0; j < k; ++j) a_ff(i, j) = chain.dense(free[i], free[j]);
    }
    const Eigen::VectorXd x_f = a_ff.llt().solve(b_f);
    // MUMPS factors in single precision: a solve is as accurate as float arithmetic allows.
    const double tolerance = GetParam() == LinearSolverType::kMumpsSingle ? 1e-6 * x_f.lpNorm<Eigen::Infinity>() : 1e-12;
    for (Eigen::Index i = 0; i < k; ++i) EXPECT_NEAR(x[free[i]], x_f[i], tolerance) << "held " << held_count;
    for (int d = 0; d < n; ++d) {
      if (held[d]) {
        EXPECT_EQ(x[d], 0.0);
      }
    }
    EXPECT_TRUE(system.FactorCovers(held));
  }
}

TEST_P(LinearSystemTest, AReducedFactorCoversOnlyTheCoordinatesItWasBuiltFor) {
  const Chain chain(20);
  const int n = chain.pattern.matrix.n;
  auto analyzed = SparseCholesky::Create(GetParam());
  analyzed->Analyze(chain.pattern.matrix);
  LinearSystem system(chain.pattern.matrix, *analyzed, GetParam());
  EXPECT_FALSE(system.FactorCovers(std::vector<char>(n, 0)));  // nothing factored yet
  std::vector<char> held(n, 0);
  for (int d = 0; d < n / 2; ++d) held[d] = 1;  // many: the reduced system
  system.Select(held);
  ASSERT_EQ(system.Factorize(chain.Held(held)), FactorStatus::kOk);
  std::vector<char> more = held;
  more[n - 1] = 1;
  EXPECT_TRUE(system.FactorCovers(more));   // fewer free coordinates: still covered
  std::vector<char> fewer = held;
  fewer[0] = 0;
  EXPECT_FALSE(system.FactorCovers(fewer));  // a coordinate it never saw
  EXPECT_GT(system.SolvesPerFactorization(), 0.0);
  system.DropFactor();
  EXPECT_FALSE(system.FactorCovers(held));
}

TEST_P(LinearSystemTest, TheLadderClimbsPastAnIndefiniteMatrix) {
  const Chain chain(10);
  auto analyzed = SparseCholesky::Create(GetParam());
  analyzed->Analyze(chain.pattern.matrix);
  LinearSystem system(chain.pattern.matrix, *analyzed, GetParam());
  system.Select(std::vector<char>(chain.pattern.matrix.n, 0));
  std::vector<double> values;
  // Indefinite unless the diagonal is shifted by at least 20 (the matrix's diagonal is about 8).
  const auto assemble = [&](double, double shift) -> const std::vector<double>& {
    values = chain.values;
    for (int j = 0; j < chain.pattern.matrix.n; ++j) values[chain.pattern.matrix.column_starts[j + 1] - 1] -= 20.0 - shift;
    return values;
  };
  const LadderResult result = FactorizeWithLadder(system, 0, 1000.0, assemble);
  EXPECT_EQ(result.status, FactorStatus::kOk);
  EXPECT_EQ(result.rung, kLadderRungs - 1);  // only the largest shift (1000 x 1.0) is enough
  EXPECT_EQ(result.factorizations, static_cast<int>(kLadderRungs));
  EXPECT_EQ(result.shifted, 4);
}

// Solvers run one per worker thread, each with its own clone of the rig's analysed factor: clones factored and
// solved at once on several threads give exactly what one thread gives (the backends keep no shared state).
TEST_P(LinearSystemTest, ClonesOnSeveralThreadsGiveExactlyWhatOneThreadGives) {
  const Chain chain(400, 10);
  const int n = chain.pattern.matrix.n;
  auto analyzed = SparseCholesky::Create(GetParam());
  analyzed->Analyze(chain.pattern.matrix);
  const auto solve = [&](int seed) {
    LinearSystem system(chain.pattern.matrix, *analyzed, GetParam());
    const std::vector<char> held(n, 0);
    system.Select(held);
    std::vector<double> values = chain.values;
    for (double& v : values) v *= 1.0 + 0.01 * seed;
    EXPECT_EQ(system.Factorize(values), FactorStatus::kOk);
    Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(n, -1.0, 1.0 + seed), x(n);
    system.Solve(b, held, &x);
    return x;
  };
  constexpr int kThreads = 4, kRounds = 5;
  std::vector<Eigen::VectorXd> serial;
  for (int t = 0; t < kThreads; ++t) serial.push_back(solve(t));
  for (int round = 0; round < kRounds; ++round) {
    std::vector<Eigen::VectorXd> parallel(kThreads);
    std::vector<std::thread> threads;
    for (int t = 0; t < kThreads; ++t) threads.emplace_back([&, t] { parallel[t] = solve(t); });
    for (std::thread& thread : threads) thread.join();
    for (int t = 0; t < kThreads; ++t) EXPECT_EQ(parallel[t], serial[t]) << "thread " << t << ", round " << round;
  }
}

// The preconditioner's solve: with CHOLMOD's factor rounded to single precision, within float rounding of the
// exact solve, and still one symmetric linear operator to double rounding (its sums are in double), so
// preconditioned conjugate gradients stay conjugate gradients; the other backends' is their solve. On a grid whose factor has
// wide supernodes with rows below them, with no, few and many held coordinates.
TEST_P(LinearSystemTest, PreconditioningIsAFixedSymmetricOperatorCloseToTheSolve) {
  GridSystem fixture(GetParam());
  const Chain& grid = fixture.grid;
  LinearSystem& system = *fixture.system;
  const int n = grid.pattern.matrix.n;
  for (const int held_count : {0, 5, n / 4}) {
    const std::vector<char> held = HeldEvery(n, held_count, 11);
    const auto free_only = [&](Eigen::VectorXd v) { return FreeOnly(std::move(v), held); };
    system.Select(held);
    ASSERT_EQ(system.Factorize(grid.Held(held)), FactorStatus::kOk);
    const Eigen::VectorXd u = free_only(Eigen::VectorXd::LinSpaced(n, 1.0, -2.0));
    Eigen::VectorXd v = free_only(Eigen::VectorXd::LinSpaced(n, 0.0, 3.0).array().sin().matrix());
    Eigen::VectorXd solved(n), pu(n), pv(n), again(n), sum(n);
    system.Solve(u, held, &solved);
    system.Precondition(u, held, &pu);
    system.Precondition(v, held, &pv);
    system.Precondition(u, held, &again);
    system.Precondition(u + v, held, &sum);
    EXPECT_EQ(pu, again) << "held " << held_count;  // deterministic
    const bool exact =
        GetParam() != LinearSolverType::kCholmodSupernodal && GetParam() != LinearSolverType::kCholmodLibrary;
    if (exact) {
      EXPECT_EQ(pu, solved) << "held " << held_count;
    } else {
      EXPECT_LT((pu - solved).norm(), 1e-5 * solved.norm()) << "held " << held_count;
      EXPECT_GT((pu - solved).norm(), 0.0) << "held " << held_count;  // the rounded factor is in use
    }
    // MUMPS solves in single precision throughout (its vectors too): not exactly linear.
    if (GetParam() == LinearSolverType::kMumpsSingle) continue;
    const double scale = u.norm() * pv.norm();
    EXPECT_NEAR(u.dot(pv), v.dot(pu), 1e-12 * scale) << "held " << held_count;
    EXPECT_LT((sum - pu - pv).norm(), 1e-12 * sum.norm()) << "held " << held_count;
    for (int d = 0; d < n; ++d) {
      if (held[d]) {
        EXPECT_EQ(pu[d], 0.0);
      }
    }
  }
}

// The Newton step after a fresh factorization (InexactNewton): the preconditioning solve, refined against the
// factored matrix to the residual asked, or the double-precision solve.
TEST_P(LinearSystemTest, SolveToReachesTheResidualAskedOrSolvesInDouble) {
  GridSystem fixture(GetParam());
  const Chain& grid = fixture.grid;
  LinearSystem& system = *fixture.system;
  const int n = grid.pattern.matrix.n;
  const bool rounded =
      GetParam() == LinearSolverType::kCholmodSupernodal || GetParam() == LinearSolverType::kCholmodLibrary;
  for (const int held_count : {0, n / 4}) {
    const std::vector<char> held = HeldEvery(n, held_count, 7);
    const auto free_only = [&](Eigen::VectorXd v) { return FreeOnly(std::move(v), held); };
    system.Select(held);
    ASSERT_EQ(system.Factorize(grid.Held(held)), FactorStatus::kOk);
    int products = 0;
    const LinearSystem::Product product = [&](const Eigen::VectorXd& v, Eigen::VectorXd* out) {
      ++products;
      *out = free_only(grid.dense * free_only(v));
    };
    const Eigen::VectorXd r = free_only(Eigen::VectorXd::LinSpaced(n, 0.0, 5.0).array().cos().matrix());
    const auto relative_residual = [&](const Eigen::VectorXd& z) {
      return (r - free_only(grid.dense * z)).norm() / r.norm();
    };
    Eigen::VectorXd exact(n), z(n);
    system.Solve(r, held, &exact);
    for (const double asked : {1e-3, 1e-10}) {
      products = 0;
      const int refinements = system.SolveTo(r, held, asked, product, &z);
      SCOPED_TRACE(::testing::Message() << "held " << held_count << ", residual asked " << asked);
      ASSERT_GE(refinements, 0);  // the refined rounded solve gets there on a well-conditioned matrix
      EXPECT_LE(relative_residual(z), asked);
      EXPECT_EQ(products, refinements + 1);
      // The rounded factor alone leaves about 1e-7 here: 1e-10 takes a refinement; an exact backend takes none.
      if (rounded && asked < 1e-8) {
        EXPECT_GE(refinements, 1);
      }
      if (!rounded && GetParam() != LinearSolverType::kMumpsSingle) {
        EXPECT_EQ(refinements, 0);
      }
      for (int d = 0; d < n; ++d) {
        if (held[d]) {
          EXPECT_EQ(z[d], 0.0);
        }
      }
    }
    // Nothing reaches a zero residual: the double-precision solve, to the bit.
    EXPECT_EQ(system.SolveTo(r, held, 0.0, product, &z), -1);
    EXPECT_EQ(z, exact);
  }
}

INSTANTIATE_TEST_SUITE_P(Backends, LinearSystemTest,
                         ::testing::Values(LinearSolverType::kCholmodSupernodal, LinearSolverType::kCholmodDouble,
                                           LinearSolverType::kEigenSimplicial, LinearSolverType::kMumpsSingle,
                                           LinearSolverType::kCholmodLibrary),
                         [](const auto& backend) {
                           std::string name = ToString(backend.param);
                           std::replace(name.begin(), name.end(), '-', '_');
                           return name;
                         });

}  // namespace
}  // namespace springblend::internal
