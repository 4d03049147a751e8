// The preconditioner's triangular solves with a CHOLMOD supernodal factor rounded to single precision: close to
// CHOLMOD's own solve, and the same to the bit whichever instruction set's kernel runs and however many threads share
// it.
#include "rounded_solve.h"

#include <cholmod.h>
#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <memory>
#include <vector>

#include "hessian_pattern.h"
#include "sparse_cholesky.h"
#include "tree_cholesky.h"

namespace springblend::internal {
namespace {

// A side x side grid of vertices with springs to eight neighbours and two steps along each axis: the 3n x 3n
// pattern of a surface's Hessian, whose separators make supernodes with many columns and rows below them. The
// values are diagonally dominant, with entries spread over several orders of magnitude (stiff and soft springs).
class GridFactor {
 public:
  explicit GridFactor(int side) {
    std::vector<int> a, b;
    for (int i = 0; i < side; ++i) {
      for (int j = 0; j < side; ++j) {
        const int v = i * side + j;
        const auto spring = [&](int w) { a.push_back(v), b.push_back(w); };
        if (j + 1 < side) spring(v + 1);
        if (i + 1 < side) spring(v + side);
        if (i + 1 < side && j + 1 < side) spring(v + side + 1);
        if (i + 1 < side && j > 0) spring(v + side - 1);
        if (j + 2 < side) spring(v + 2);
        if (i + 2 < side) spring(v + 2 * side);
      }
    }
    pattern_ = HessianPattern::Build(side * side, a, b);
    const SymmetricPattern& m = pattern_.matrix;
    values_.assign(m.row_indices.size(), 0.0);
    std::vector<double> row_sum(m.n, 0.0);
    for (int j = 0; j < m.n; ++j) {
      for (int k = m.column_starts[j]; k < m.column_starts[j + 1]; ++k) {
        const int i = m.row_indices[k];
        if (i == j) continue;
        // Deterministic pseudo-random magnitudes over four decades, both signs.
        const double u = std::sin(12.9898 * i + 78.233 * j) * 43758.5453;
        const double f = u - std::floor(u);
        values_[k] = (f < 0.5 ? -1.0 : 1.0) * std::pow(10.0, 4.0 * f - 2.0);
        row_sum[i] += std::abs(values_[k]);
        row_sum[j] += std::abs(values_[k]);
      }
    }
    for (int j = 0; j < m.n; ++j) {
      for (int k = m.column_starts[j]; k < m.column_starts[j + 1]; ++k) {
        if (m.row_indices[k] == j) values_[k] = row_sum[j] + 1e-3;
      }
    }
    cholmod_start(&common_);
    common_.supernodal = CHOLMOD_SUPERNODAL;
    cholmod_sparse s{};
    s.nrow = s.ncol = m.n;
    s.nzmax = m.row_indices.size();
    s.p = const_cast<int*>(m.column_starts.data());  // NOLINT: read only
    s.i = const_cast<int*>(m.row_indices.data());    // NOLINT: read only
    s.x = values_.data();
    s.stype = 1;
    s.itype = CHOLMOD_INT;
    s.xtype = CHOLMOD_REAL;
    s.dtype = CHOLMOD_DOUBLE;
    s.sorted = s.packed = 1;
    factor_ = cholmod_analyze(&s, &common_);
    cholmod_factorize(&s, factor_, &common_);
    const double* x = static_cast<const double*>(factor_->x);
    floats_.assign(x, x + factor_->xsize);
    view_.n = m.n;
    view_.nsuper = static_cast<int>(factor_->nsuper);
    view_.perm = static_cast<const int*>(factor_->Perm);
    view_.super = static_cast<const int*>(factor_->super);
    view_.pi = static_cast<const int*>(factor_->pi);
    view_.px = static_cast<const int*>(factor_->px);
    view_.rows = static_cast<const int*>(factor_->s);
    view_.values = floats_.data();
    workspace_.Fit(view_, static_cast<int>(factor_->maxesize));
    schedule_ = PlanSolve(view_);
  }
  ~GridFactor() {
    cholmod_free_factor(&factor_, &common_);
    cholmod_finish(&common_);
  }
  GridFactor(const GridFactor&) = delete;
  GridFactor& operator=(const GridFactor&) = delete;

  int n() const { return view_.n; }
  int widest() const { return MaxSupernodeColumns(view_); }
  int nsuper() const { return view_.nsuper; }
  Eigen::VectorXd Exact(const Eigen::VectorXd& b) {
    cholmod_dense rhs{};
    rhs.nrow = rhs.nzmax = rhs.d = n();
    rhs.ncol = 1;
    rhs.x = const_cast<double*>(b.data());  // NOLINT: read only
    rhs.xtype = CHOLMOD_REAL;
    rhs.dtype = CHOLMOD_DOUBLE;
    cholmod_dense* x = cholmod_solve(CHOLMOD_A, factor_, &rhs, &common_);
    Eigen::VectorXd out = Eigen::Map<const Eigen::VectorXd>(static_cast<const double*>(x->x), n());
    cholmod_free_dense(&x, &common_);
    return out;
  }
  // With the schedule (shared between the threads of the caller's arena) or in one thread.
  Eigen::VectorXd Single(const Eigen::VectorXd& b, KernelIsa isa, bool scheduled = true) {
    Eigen::VectorXd x(n());
    RoundedSupernodalSolve(view_, scheduled ? &schedule_ : nullptr, b.data(), x.data(), &workspace_, isa);
    return x;
  }
  const SolveSchedule& schedule() const { return schedule_; }
  const SymmetricPattern& pattern() const { return pattern_.matrix; }
  const std::vector<double>& values() const { return values_; }
  SupernodalFactor structure() const {
    SupernodalFactor s = view_;
    s.values = nullptr;
    return s;
  }
  // CHOLMOD's own double factor.
  const double* cholmod_entries() const { return static_cast<const double*>(factor_->x); }
  size_t entries() const { return factor_->xsize; }

 private:
  HessianPattern pattern_;
  std::vector<double> values_;
  cholmod_common common_{};
  cholmod_factor* factor_ = nullptr;
  std::vector<float> floats_;
  SupernodalFactor view_;
  SolveWorkspace workspace_;
  SolveSchedule schedule_;
};

TEST(RoundedSolve, ASinglePrecisionFactorSolvesCloseToTheDoubleFactor) {
  GridFactor grid(30);
  ASSERT_GT(grid.widest(), 8);  // supernodes wide enough for the kernels' four-column and eight-lane paths
  const Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(grid.n(), -1.0, 2.0).array().cos().matrix();
  const Eigen::VectorXd exact = grid.Exact(b);
  for (const bool scheduled : {false, true}) {
    const Eigen::VectorXd single = grid.Single(b, BestKernelIsa(), scheduled);
    // A float keeps 24 significant bits: the factor's rounding, times the (small) condition of this system.
    EXPECT_LT((single - exact).norm(), 1e-6 * exact.norm()) << "scheduled " << scheduled;
    EXPECT_GT((single - exact).norm(), 0.0);  // the rounded factor is what was read
  }
}

TEST(RoundedSolve, EveryInstructionSetGivesTheSameBits) {
  GridFactor grid(30);
  const Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(grid.n(), 3.0, -5.0).array().sin().matrix();
  const Eigen::VectorXd single = grid.Single(b, KernelIsa::kGeneric);
  for (const KernelIsa isa : {KernelIsa::kAvx2, KernelIsa::kAvx512}) {
    // On a machine without the instruction set the generic kernel runs, and the test holds trivially.
    const Eigen::VectorXd s = grid.Single(b, isa);
    for (int i = 0; i < grid.n(); ++i) {
      ASSERT_EQ(s[i], single[i]) << "single, isa " << static_cast<int>(isa) << ", entry " << i;
    }
  }
}

// The schedule comes from the factor's structure alone: two threads, one thread, and any instruction set give the
// same bits, and the tree's top and its two bins together cover every supernode once.
TEST(RoundedSolve, TwoThreadsGiveTheSameBitsAsOne) {
  GridFactor grid(40);
  const SolveSchedule& plan = grid.schedule();
  ASSERT_TRUE(plan.parallel);
  EXPECT_GT(plan.bin_entries[0], 0);
  EXPECT_GT(plan.bin_entries[1], 0);
  EXPECT_EQ(plan.top_entries + plan.bin_entries[0] + plan.bin_entries[1], plan.entries);
  std::vector<int> seen(static_cast<size_t>(grid.nsuper()), 0);
  for (int s : plan.top) ++seen[static_cast<size_t>(s)];
  for (const auto& bin : plan.bins) {
    for (const auto& [first, end] : bin) {
      for (int s = first; s < end; ++s) ++seen[static_cast<size_t>(s)];
    }
  }
  for (int s = 0; s < grid.nsuper(); ++s) ASSERT_EQ(seen[static_cast<size_t>(s)], 1) << "supernode " << s;
  // Some of the top's supernodes are wide enough to be split between the threads.
  EXPECT_GT(grid.widest(), 16);

  const Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(grid.n(), -2.0, 7.0).array().sin().matrix();
  Eigen::VectorXd one, two;
  tbb::task_arena(1).execute([&] { one = grid.Single(b, KernelIsa::kGeneric); });
  for (int round = 0; round < 3; ++round) {
    for (const KernelIsa isa : {KernelIsa::kGeneric, KernelIsa::kAvx2, KernelIsa::kAvx512}) {
      tbb::task_arena(2).execute([&] { two = grid.Single(b, isa); });
      for (int i = 0; i < grid.n(); ++i) ASSERT_EQ(two[i], one[i]) << "round " << round << ", entry " << i;
    }
  }
  // Summing the bins' updates apart changes the rounding only: the sequential solve is within a float's.
  const Eigen::VectorXd sequential = grid.Single(b, KernelIsa::kGeneric, false);
  EXPECT_LT((one - sequential).norm(), 1e-12 * sequential.norm());
}

// The numeric factorization shared by two threads along the tree: CHOLMOD's factor to rounding, the same bits with
// one thread or two, and a negative pivot found in a bin's subtree or at the top.
TEST(TreeCholesky, FactorsAsCholmodWithTheSameBitsOnOneThreadOrTwo) {
  GridFactor grid(40);
  const std::shared_ptr<const TreeCholesky> tree = TreeCholesky::Plan(grid.structure(), grid.pattern());
  ASSERT_NE(tree, nullptr);
  ASSERT_TRUE(tree->split().parallel);
  EXPECT_GT(tree->split().bin_work[0], 0.0);
  EXPECT_GT(tree->split().bin_work[1], 0.0);
  std::vector<double> one(grid.entries()), two(grid.entries());
  TreeCholesky::Workspace workspace;
  tbb::task_arena(1).execute([&] { ASSERT_TRUE(tree->Factorize(grid.structure(), grid.values().data(), one.data(), &workspace)); });
  const double* reference = grid.cholmod_entries();
  double largest = 0.0, off = 0.0;
  for (size_t k = 0; k < one.size(); ++k) {
    largest = std::max(largest, std::abs(reference[k]));
    off = std::max(off, std::abs(one[k] - reference[k]));
  }
  EXPECT_GT(largest, 0.0);
  EXPECT_LT(off, 1e-12 * largest);
  for (int round = 0; round < 3; ++round) {
    std::fill(two.begin(), two.end(), -1.0);
    tbb::task_arena(2).execute([&] { ASSERT_TRUE(tree->Factorize(grid.structure(), grid.values().data(), two.data(), &workspace)); });
    for (size_t k = 0; k < one.size(); ++k) ASSERT_EQ(two[k], one[k]) << "round " << round << ", entry " << k;
  }
}

TEST(TreeCholesky, FindsANegativePivotInABinAndAtTheTop) {
  GridFactor grid(40);
  const SupernodalFactor structure = grid.structure();
  const std::shared_ptr<const TreeCholesky> tree = TreeCholesky::Plan(structure, grid.pattern());
  ASSERT_NE(tree, nullptr);
  const TreeSplit& split = tree->split();
  ASSERT_FALSE(split.top.empty());
  ASSERT_FALSE(split.bins[1].empty());
  // A column of the factor in the second bin's first subtree, and the top's last one.
  const int in_bin = structure.super[split.bins[1].front().first];
  const int at_top = structure.super[split.top.back() + 1] - 1;
  const SymmetricPattern& pattern = grid.pattern();
  std::vector<double> lx(grid.entries());
  TreeCholesky::Workspace workspace;
  for (const int column : {in_bin, at_top}) {
    std::vector<double> values = grid.values();
    const int j = structure.perm[column];  // A's column
    for (int k = pattern.column_starts[j]; k < pattern.column_starts[j + 1]; ++k) {
      if (pattern.row_indices[k] == j) values[k] = -values[k];
    }
    EXPECT_FALSE(tree->Factorize(structure, values.data(), lx.data(), &workspace)) << "column " << column;
  }
  EXPECT_TRUE(tree->Factorize(structure, grid.values().data(), lx.data(), &workspace));
}

// The production backend factors with it: its solves match CHOLMOD's own factor's, a clone gives the same bits, and
// an indefinite matrix is reported so.
TEST(TreeCholesky, TheCholmodBackendSolvesWithItAndItsClones) {
  GridFactor grid(40);
  std::unique_ptr<SparseCholesky> backend = SparseCholesky::Create(LinearSolverType::kCholmodSupernodal);
  backend->Analyze(grid.pattern());
  std::unique_ptr<SparseCholesky> clone = backend->Clone();
  ASSERT_EQ(backend->Factorize(grid.values().data()), FactorStatus::kOk);
  ASSERT_EQ(clone->Factorize(grid.values().data()), FactorStatus::kOk);
  const Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(grid.n(), 1.0, -4.0).array().cos().matrix();
  const Eigen::VectorXd exact = grid.Exact(b);
  Eigen::VectorXd x(grid.n()), y(grid.n());
  backend->Solve(b.data(), x.data());
  clone->Solve(b.data(), y.data());
  EXPECT_LT((x - exact).norm(), 1e-12 * exact.norm());
  for (int i = 0; i < grid.n(); ++i) ASSERT_EQ(x[i], y[i]) << "entry " << i;
  std::vector<double> values = grid.values();
  const SymmetricPattern& pattern = grid.pattern();
  for (int k = pattern.column_starts[7]; k < pattern.column_starts[8]; ++k) {
    if (pattern.row_indices[k] == 7) values[k] = -1e6;
  }
  EXPECT_EQ(backend->Factorize(values.data()), FactorStatus::kNotPositiveDefinite);
  ASSERT_EQ(backend->Factorize(grid.values().data()), FactorStatus::kOk);
  backend->Solve(b.data(), y.data());
  for (int i = 0; i < grid.n(); ++i) ASSERT_EQ(x[i], y[i]) << "entry " << i;
}

}  // namespace
}  // namespace springblend::internal
