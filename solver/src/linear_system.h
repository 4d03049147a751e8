// The Newton system's linear algebra for a set of held coordinates: the full 3n x 3n matrix with identity
// rows and columns for held coordinates, or, when many are held (a placement solve holds the whole surface;
// contacts and pins pile up), the matrix reduced to the free ones, analysed once per held set. It keeps the
// last successful factorization, which inexact Newton reuses as a preconditioner while it still covers the
// free coordinates.
#pragma once

#include <Eigen/Core>
#include <functional>
#include <memory>
#include <vector>

#include "sparse_cholesky.h"

namespace springblend::internal {

class LinearSystem {
 public:
  // `full` is the Hessian pattern; `analyzed` its symbolic factorization, cloned here.
  LinearSystem(const SymmetricPattern& full, const SparseCholesky& analyzed, LinearSolverType type);
  ~LinearSystem();

  // Chooses the full or the reduced system for these held coordinates (1 = held), analysing a reduced
  // pattern when the held set changed since the last reduced one.
  void Select(const std::vector<char>& held);
  // Factorizes the selected system from the full matrix's values. On success the factor is kept.
  FactorStatus Factorize(const std::vector<double>& full_values);
  // z = A^{-1} r with the kept factor, restricted to the free coordinates of `held` (zero on held ones).
  void Solve(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z);
  // The same with the factor rounded to single precision where the backend keeps such a copy (CHOLMOD):
  // for preconditioning conjugate gradients, and for a Newton step only once its residual in the factored system
  // is checked (SolveTo refines it, or solves in double).
  void Precondition(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z);

  // A step with the kept factor to a relative residual: z from Precondition, refined (z += P^{-1} (r - A z)) until
  // |r - A z| <= relative_residual |r|, where `product` gives A z (the factored matrix, on the free coordinates);
  // after two refinements that fall short, the double-precision Solve. Returns the refinements made, or -1 for
  // the Solve. `relative_residual` 0 always ends in the Solve.
  using Product = std::function<void(const Eigen::VectorXd& v, Eigen::VectorXd* product)>;
  int SolveTo(const Eigen::VectorXd& r, const std::vector<char>& held, double relative_residual,
              const Product& product, Eigen::VectorXd* z);

  bool has_factor() const { return kept_; }
  // Whether the kept factor can precondition a system with these held coordinates: the full system's
  // (identity rows) covers any free set; a reduced one only the free coordinates it was built for.
  bool FactorCovers(const std::vector<char>& held) const;
  // About how many solves with the kept factor cost as much as factorizing it again.
  double SolvesPerFactorization() const;
  // Forget the kept factor (the next Newton step factorizes afresh).
  void DropFactor() { kept_ = false; }

 private:
  struct Reduced;
  void Apply(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z, bool rounded);
  const SymmetricPattern& full_;
  LinearSolverType type_;
  std::unique_ptr<SparseCholesky> cholesky_;  // the full system
  std::unique_ptr<Reduced> reduced_;
  Eigen::VectorXd residual_, correction_;  // SolveTo's workspace
  bool use_reduced_ = false;
  bool kept_ = false;
  bool kept_reduced_ = false;
};

// The factorization ladder. The true Hessian converges quadratically but is indefinite where springs are
// compressed; when its Cholesky fails, halve the compressed springs' negative transverse stiffness, then
// drop it (projected Newton). The projected Hessian is still singular where the surface is flat at rest, so
// the last rungs add a growing Levenberg-Marquardt shift to the diagonal.
struct LadderRung {
  double negative_scale;  // 1: true Hessian, 0: projected
  double shift;           // diagonal shift in units of the mean stiffness 1 / mean rest length
};
inline constexpr LadderRung kLadder[] = {{1.0, 0.0}, {0.5, 0.0}, {0.0, 0.0}, {0.0, 1e-6},
                                         {0.0, 1e-4}, {0.0, 1e-2}, {0.0, 1.0}};
inline constexpr size_t kLadderRungs = sizeof(kLadder) / sizeof(kLadder[0]);
inline constexpr size_t kFirstProjectedRung = 2;

struct LadderResult {
  FactorStatus status = FactorStatus::kFailed;
  size_t rung = 0;  // the rung that succeeded (or the last tried)
  double shift = 0.0;  // that rung's absolute diagonal shift (as given to assemble)
  int factorizations = 0, projected = 0, shifted = 0;
};

// Climbs from rung `first`: assemble(negative_scale, absolute shift) fills the full values, then the
// selected system is factorized, until one is positive definite.
LadderResult FactorizeWithLadder(
    LinearSystem& system, size_t first, double mean_stiffness,
    const std::function<const std::vector<double>&(double negative_scale, double shift)>& assemble);

}  // namespace springblend::internal
