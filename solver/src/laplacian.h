// The scalar projective-dynamics matrix L = sum_q k_q (e_a - e_b)(e_a - e_b)^T of a spring system (n x n,
// a ninth of the 3n x 3n Hessian's entries), with the rig's always-held vertices (fixed ones, the anchor)
// eliminated and a tiny diagonal so a floating rig's is definite. Factorized once per solver from the rest
// shape's stiffness, it is a preconditioner (metric) for the frame's true Hessian: the same for x, y and z,
// applied to the three coordinates at once.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "sparse_cholesky.h"
#include "spring_system.h"

namespace springblend::internal {

class LaplacianPreconditioner {
 public:
  // stiffness: k_q per spring; always_held: vertices held in every frame (not part of L).
  LaplacianPreconditioner(const SpringTopology& topology, const std::vector<double>& stiffness,
                          const std::vector<int>& always_held, LinearSolverType type);
  ~LaplacianPreconditioner();
  bool ok() const { return ok_; }
  // z = L^{-1} r per coordinate, zero on held coordinates (r stacked 3n).
  void Apply(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z);
  long factor_nonzeros() const { return cholesky_ ? cholesky_->FactorNonzeros() : 0; }

 private:
  std::vector<int> index_;  // vertex -> row of L, or -1 (always held)
  SymmetricPattern pattern_;
  std::unique_ptr<SparseCholesky> cholesky_;
  bool ok_ = false;
  Eigen::VectorXd rhs_, solution_;
};

}  // namespace springblend::internal
