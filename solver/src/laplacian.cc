#include "laplacian.h"

#include <algorithm>
#include <map>

namespace springblend::internal {

LaplacianPreconditioner::LaplacianPreconditioner(const SpringTopology& topology, const std::vector<double>& stiffness,
                                                 const std::vector<int>& always_held, LinearSolverType type) {
  const int n = topology.vertices;
  index_.assign(n, 0);
  for (int v : always_held) index_[v] = -1;
  int rows = 0;
  for (int v = 0; v < n; ++v) index_[v] = index_[v] < 0 ? -1 : rows++;
  // Upper triangle by columns: for column j, the springs (i, j) with i < j among free vertices, and (j, j).
  std::vector<std::map<int, double>> columns(rows);
  double mean_k = 0.0;
  for (int q = 0; q < topology.springs(); ++q) {
    const double k = stiffness[q];
    mean_k += k;
    const int a = index_[topology.a[q]], b = index_[topology.b[q]];
    if (a >= 0) columns[a][a] += k;
    if (b >= 0) columns[b][b] += k;
    if (a >= 0 && b >= 0) columns[std::max(a, b)][std::min(a, b)] -= k;
  }
  mean_k /= std::max(topology.springs(), 1);
  pattern_.n = rows;
  std::vector<double> values;
  for (int j = 0; j < rows; ++j) {
    pattern_.column_starts.push_back(static_cast<int>(pattern_.row_indices.size()));
    columns[j][j] += 1e-8 * mean_k;  // definite even where nothing is held
    for (const auto& [i, value] : columns[j]) {
      pattern_.row_indices.push_back(i);
      values.push_back(value);
    }
  }
  pattern_.column_starts.push_back(static_cast<int>(pattern_.row_indices.size()));
  cholesky_ = SparseCholesky::Create(type);
  cholesky_->Analyze(pattern_);
  ok_ = cholesky_->Factorize(values.data()) == FactorStatus::kOk;
  rhs_.resize(rows);
  solution_.resize(rows);
}

LaplacianPreconditioner::~LaplacianPreconditioner() = default;

void LaplacianPreconditioner::Apply(const Eigen::VectorXd& r, const std::vector<char>& held, Eigen::VectorXd* z) {
  const Eigen::Index n = static_cast<Eigen::Index>(index_.size());
  z->setZero(3 * n);
  for (int c = 0; c < 3; ++c) {
    for (Eigen::Index v = 0; v < n; ++v) {
      if (index_[v] >= 0) rhs_[index_[v]] = held[3 * v + c] ? 0.0 : r[3 * v + c];
    }
    cholesky_->Solve(rhs_.data(), solution_.data());
    for (Eigen::Index v = 0; v < n; ++v) {
      if (index_[v] >= 0 && !held[3 * v + c]) (*z)[3 * v + c] = solution_[index_[v]];
    }
  }
}

}  // namespace springblend::internal
