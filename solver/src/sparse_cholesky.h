// The sparse Cholesky backend behind one small interface (the only place that knows which library
// factors). The pattern is analysed once per rig; each solver clones the analysed object and refactors
// numerically as the values change.
#pragma once

#include <memory>

#include "springblend/rig.h"

namespace springblend::internal {

// A symmetric matrix stored as its upper triangle in compressed sparse columns, 0-based, sorted rows.
struct SymmetricPattern {
  int n = 0;
  std::vector<int> column_starts;  // n + 1 entries
  std::vector<int> row_indices;    // column_starts[n] entries
};

enum class FactorStatus { kOk, kNotPositiveDefinite, kFailed };

class SparseCholesky {
 public:
  virtual ~SparseCholesky() = default;
  static std::unique_ptr<SparseCholesky> Create(LinearSolverType type);

  // Symbolic analysis (fill-reducing ordering, elimination tree, supernodes). The pattern must outlive
  // this object and every clone of it.
  virtual void Analyze(const SymmetricPattern& pattern) = 0;
  // A new object holding its own copy of the analysis, ready for Factorize.
  virtual std::unique_ptr<SparseCholesky> Clone() const = 0;
  // Numeric factorization of the matrix with the analysed pattern and these values (same layout).
  virtual FactorStatus Factorize(const double* values) = 0;
  // x = A^{-1} b after a successful Factorize. b and x may alias.
  virtual void Solve(const double* b, double* x) = 0;
  // z ~ A^{-1} b for a preconditioner, after a successful Factorize: may read a copy of the factor rounded to
  // single precision (half the memory a solve streams; a solve is bound by memory). Its error is the
  // rounding's, about 1e-7 of L's entries times the condition, so it is never an answer. Default: Solve.
  virtual void Precondition(const double* b, double* x) { Solve(b, x); }
  // Nonzeros of the factor L (after analysis).
  virtual long FactorNonzeros() const = 0;
  // About how many solves with the factor cost as much as one numeric factorization (from the analysis's
  // flop counts; a solve reads L twice). Deterministic, unlike a clock.
  virtual double SolvesPerFactorization() const = 0;
};

}  // namespace springblend::internal
