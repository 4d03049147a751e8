#include "linear_system.h"

#include <algorithm>

namespace springblend::internal {

struct LinearSystem::Reduced {
  std::vector<char> held;  // the held mask it was built for
  SymmetricPattern pattern;
  std::vector<int> gather;  // reduced entry -> full value slot
  std::vector<int> dofs;    // reduced unknown -> full coordinate
  std::unique_ptr<SparseCholesky> cholesky;
  std::vector<double> values;
  Eigen::VectorXd rhs, solution;
};

LinearSystem::LinearSystem(const SymmetricPattern& full, const SparseCholesky& analyzed, LinearSolverType type)
    : full_(full), type_(type), cholesky_(analyzed.Clone()) {}

LinearSystem::~LinearSystem() = default;

void LinearSystem::Select(const std::vector<char>& held) {
  // Holding a few coordinates (the anchor, a gauge) costs nothing in the full system; holding many makes a
  // smaller system worthwhile.
  const size_t count = static_cast<size_t>(std::count(held.begin(), held.end(), 1));
  use_reduced_ = count * 10 > held.size();
  if (!use_reduced_ || (reduced_ && reduced_->held == held)) return;
  auto reduced = std::make_unique<Reduced>();
  reduced->held = held;
  std::vector<int> index(full_.n, -1);
  for (int d = 0; d < full_.n; ++d) {
    if (!held[d]) {
      index[d] = static_cast<int>(reduced->dofs.size());
      reduced->dofs.push_back(d);
    }
  }
  SymmetricPattern& p = reduced->pattern;
  p.n = static_cast<int>(reduced->dofs.size());
  p.column_starts.reserve(p.n + 1);
  for (int j : reduced->dofs) {
    p.column_starts.push_back(static_cast<int>(p.row_indices.size()));
    for (int k = full_.column_starts[j]; k < full_.column_starts[j + 1]; ++k) {
      const int i = full_.row_indices[k];
      if (index[i] < 0) continue;
      p.row_indices.push_back(index[i]);  // index is increasing, so rows stay sorted
      reduced->gather.push_back(k);
    }
  }
  p.column_starts.push_back(static_cast<int>(p.row_indices.size()));
  reduced->cholesky = SparseCholesky::Create(type_);
  reduced->cholesky->Analyze(reduced->pattern);
  reduced->values.resize(reduced->gather.size());
  reduced->rhs.resize(p.n);
  reduced->solution.resize(p.n);
  // A kept reduced factor belongs to the system being replaced.
  if (kept_ && kept_reduced_) kept_ = false;
  reduced_ = std::move(reduced);
}

FactorStatus LinearSystem::Factorize(const std::vector<double>& full_values) {
  kept_ = false;
  FactorStatus status;
  if (!use_reduced_) {
    status = cholesky_->Factorize(full_values.data());
  } else {
    Reduced& r = *reduced_;
    for (size_t e = 0; e < r.gather.size(); ++e) r.values[e] = full_values[r.gather[e]];
    status = r.cholesky->Factorize(r.values.data());
  }
  if (status == FactorStatus::kOk) {
    kept_ = true;
    kept_reduced_ = use_reduced_;
  }
  return status;
}

void LinearSystem::Solve(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z) {
  Apply(r, held, z, false);
}

void LinearSystem::Precondition(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z) {
  Apply(r, held, z, true);
}

void LinearSystem::Apply(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z,
                         bool rounded) {
  if (kept_reduced_) {
    Reduced& red = *reduced_;
    for (size_t i = 0; i < red.dofs.size(); ++i) red.rhs[static_cast<Eigen::Index>(i)] = r[red.dofs[i]];
    if (rounded) {
      red.cholesky->Precondition(red.rhs.data(), red.solution.data());
    } else {
      red.cholesky->Solve(red.rhs.data(), red.solution.data());
    }
    z->setZero();
    for (size_t i = 0; i < red.dofs.size(); ++i) (*z)[red.dofs[i]] = red.solution[static_cast<Eigen::Index>(i)];
  } else if (rounded) {
    cholesky_->Precondition(r.data(), z->data());
  } else {
    cholesky_->Solve(r.data(), z->data());
  }
  // Restricted to the free coordinates, an SPD preconditioner stays SPD.
  for (Eigen::Index d = 0; d < z->size(); ++d) {
    if (held[d]) (*z)[d] = 0.0;
  }
}

int LinearSystem::SolveTo(const Eigen::VectorXd& r, const std::vector<char>& held, double relative_residual,
                          const Product& product, Eigen::VectorXd* z) {
  const double target = relative_residual * r.norm();
  residual_.resize(r.size());
  correction_.resize(r.size());
  Precondition(r, held, z);
  for (int refinements = 0;; ++refinements) {
    product(*z, &residual_);
    residual_ = r - residual_;
    for (Eigen::Index d = 0; d < residual_.size(); ++d) {
      if (held[d]) residual_[d] = 0.0;
    }
    if (residual_.norm() <= target) return refinements;
    if (refinements == 2) break;
    Precondition(residual_, held, &correction_);
    *z += correction_;
  }
  Solve(r, held, z);
  return -1;
}

bool LinearSystem::FactorCovers(const std::vector<char>& held) const {
  if (!kept_) return false;
  if (!kept_reduced_) return true;
  const std::vector<char>& built = reduced_->held;
  for (size_t d = 0; d < held.size(); ++d) {
    if (!held[d] && built[d]) return false;
  }
  return true;
}

double LinearSystem::SolvesPerFactorization() const {
  return (kept_reduced_ ? *reduced_->cholesky : *cholesky_).SolvesPerFactorization();
}

LadderResult FactorizeWithLadder(
    LinearSystem& system, size_t first, double mean_stiffness,
    const std::function<const std::vector<double>&(double negative_scale, double shift)>& assemble) {
  LadderResult result;
  for (size_t i = first; i < kLadderRungs; ++i) {
    const LadderRung& rung = kLadder[i];
    result.shift = rung.shift * mean_stiffness;
    const std::vector<double>& values = assemble(rung.negative_scale, result.shift);
    result.status = system.Factorize(values);
    ++result.factorizations;
    if (rung.negative_scale < 1.0) ++result.projected;
    if (rung.shift > 0.0) ++result.shifted;
    result.rung = i;
    if (result.status != FactorStatus::kNotPositiveDefinite) break;
  }
  return result;
}

}  // namespace springblend::internal
