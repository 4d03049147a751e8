#include "tree_cholesky.h"

#include <tbb/parallel_invoke.h>

#include <algorithm>
#include <atomic>
#include <cstddef>

extern "C" {
void dsyrk_(const char* uplo, const char* trans, const int* n, const int* k, const double* alpha, const double* a,
            const int* lda, const double* beta, double* c, const int* ldc);
void dgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const double* alpha,
            const double* a, const int* lda, const double* b, const int* ldb, const double* beta, double* c,
            const int* ldc);
void dtrsm_(const char* side, const char* uplo, const char* transa, const char* diag, const int* m, const int* n,
            const double* alpha, const double* a, const int* lda, double* b, const int* ldb);
void dpotrf_(const char* uplo, const int* n, double* a, const int* lda, int* info);
}

namespace springblend::internal {
namespace {

// A top supernode's updates are split between the threads when they cost at least this many flops (a hand-over
// costs a few microseconds; this is about a tenth of a millisecond of BLAS).
constexpr double kWideFlops = 1e6;

}  // namespace

std::shared_ptr<const TreeCholesky> TreeCholesky::Plan(const SupernodalFactor& structure,
                                                       const SymmetricPattern& pattern) {
  const int n = structure.n, nsuper = structure.nsuper;
  if (n <= 0 || nsuper <= 1 || pattern.n != n || structure.perm == nullptr) return nullptr;
  auto plan = std::shared_ptr<TreeCholesky>(new TreeCholesky());
  TreeCholesky& t = *plan;
  t.n_ = n;
  t.nsuper_ = nsuper;
  const int* super = structure.super;
  const int* pi = structure.pi;
  const int* rows = structure.rows;
  // Each supernode's rows: its own columns first, then increasing.
  std::vector<int> node_of(static_cast<size_t>(n), -1);
  for (int s = 0; s < nsuper; ++s) {
    const int nscol = super[s + 1] - super[s];
    for (int j = 0; j < nscol; ++j) {
      if (rows[pi[s] + j] != super[s] + j) return nullptr;
      node_of[static_cast<size_t>(super[s] + j)] = s;
    }
    for (int p = pi[s] + 1; p < pi[s + 1]; ++p) {
      if (rows[p] <= rows[p - 1]) return nullptr;
    }
  }
  // A's entries, each to its place in L's blocks: (i, j) of A is (pinv i, pinv j) of P A P^T.
  std::vector<int> pinv(static_cast<size_t>(n));
  for (int k = 0; k < n; ++k) pinv[static_cast<size_t>(structure.perm[k])] = k;
  const int entries = pattern.column_starts[static_cast<size_t>(n)];
  std::vector<int> entry_node(static_cast<size_t>(entries)), column_of(static_cast<size_t>(entries));
  t.a_start_.assign(static_cast<size_t>(nsuper) + 1, 0);
  for (int j = 0; j < n; ++j) {
    for (int k = pattern.column_starts[static_cast<size_t>(j)]; k < pattern.column_starts[static_cast<size_t>(j) + 1];
         ++k) {
      const int a = pinv[static_cast<size_t>(pattern.row_indices[static_cast<size_t>(k)])];
      const int b = pinv[static_cast<size_t>(j)];
      const int s = node_of[static_cast<size_t>(std::min(a, b))];
      entry_node[static_cast<size_t>(k)] = s;
      column_of[static_cast<size_t>(k)] = j;
      ++t.a_start_[static_cast<size_t>(s) + 1];
    }
  }
  for (int s = 0; s < nsuper; ++s) t.a_start_[static_cast<size_t>(s) + 1] += t.a_start_[static_cast<size_t>(s)];
  t.a_dest_.resize(static_cast<size_t>(entries));
  t.a_src_.resize(static_cast<size_t>(entries));
  {
    std::vector<long> next(t.a_start_.begin(), t.a_start_.end() - 1);
    for (int k = 0; k < entries; ++k) t.a_src_[static_cast<size_t>(next[static_cast<size_t>(entry_node[static_cast<size_t>(k)])]++)] = k;
  }
  std::vector<int> map(static_cast<size_t>(n), -1);
  for (int s = 0; s < nsuper; ++s) {
    const int nsrow = pi[s + 1] - pi[s];
    for (int p = 0; p < nsrow; ++p) map[static_cast<size_t>(rows[pi[s] + p])] = p;
    for (long e = t.a_start_[static_cast<size_t>(s)]; e < t.a_start_[static_cast<size_t>(s) + 1]; ++e) {
      const int k = t.a_src_[static_cast<size_t>(e)];
      const int a = pinv[static_cast<size_t>(pattern.row_indices[static_cast<size_t>(k)])];
      const int b = pinv[static_cast<size_t>(column_of[static_cast<size_t>(k)])];
      const int row = std::max(a, b), col = std::min(a, b);
      const int local = map[static_cast<size_t>(row)];
      if (local < 0 || rows[pi[s] + local] != row) return nullptr;  // not in the analysed structure
      t.a_dest_[static_cast<size_t>(e)] =
          structure.px[s] + static_cast<long>(col - super[s]) * nsrow + local;
    }
    for (int p = 0; p < nsrow; ++p) map[static_cast<size_t>(rows[pi[s] + p])] = -1;
  }
  // The updates: supernode d's rows below its diagonal block, in runs by the supernode holding them.
  std::vector<Update> found;
  std::vector<int> target;
  std::vector<double> received(static_cast<size_t>(nsuper), 0.0);
  t.u_start_.assign(static_cast<size_t>(nsuper) + 1, 0);
  for (int d = 0; d < nsuper; ++d) {
    const int nscol = super[d + 1] - super[d], nsrow = pi[d + 1] - pi[d];
    int p = nscol;
    while (p < nsrow) {
      const int s = node_of[static_cast<size_t>(rows[pi[d] + p])];
      const int p1 = p;
      while (p < nsrow && node_of[static_cast<size_t>(rows[pi[d] + p])] == s) ++p;
      found.push_back({d, p1, p});
      target.push_back(s);
      ++t.u_start_[static_cast<size_t>(s) + 1];
      const double m = nsrow - p1, k = p - p1;
      received[static_cast<size_t>(s)] += m * k * nscol;
      t.c_size_ = std::max(t.c_size_, static_cast<size_t>(m * k));
    }
  }
  for (int s = 0; s < nsuper; ++s) t.u_start_[static_cast<size_t>(s) + 1] += t.u_start_[static_cast<size_t>(s)];
  t.updates_.resize(found.size());
  {
    std::vector<long> next(t.u_start_.begin(), t.u_start_.end() - 1);
    for (size_t u = 0; u < found.size(); ++u) t.updates_[static_cast<size_t>(next[static_cast<size_t>(target[u])]++)] = found[u];
  }
  // Work per supernode: the updates it receives, its diagonal block's factorization and the solve of its rows below.
  std::vector<double> own(static_cast<size_t>(nsuper)), shared(static_cast<size_t>(nsuper));
  t.wide_.assign(static_cast<size_t>(nsuper), 0);
  for (int s = 0; s < nsuper; ++s) {
    const double nscol = super[s + 1] - super[s], below = (pi[s + 1] - pi[s]) - nscol;
    const double update = received[static_cast<size_t>(s)], trsm = below * nscol * nscol;
    own[static_cast<size_t>(s)] = update + nscol * nscol * nscol / 3.0 + trsm;
    const bool wide = update + trsm >= kWideFlops && nscol >= 8;
    t.wide_[static_cast<size_t>(s)] = wide ? 1 : 0;
    shared[static_cast<size_t>(s)] = own[static_cast<size_t>(s)] - (wide ? 0.5 * (update + trsm) : 0.0);
  }
  t.split_ = SplitTree(structure, own, shared);
  if (!t.split_.parallel) return nullptr;
  return plan;
}

void TreeCholesky::Assemble(const SupernodalFactor& f, int s, const double* values, double* lx) const {
  const long nscol = f.super[s + 1] - f.super[s];
  const long nsrow = f.pi[s + 1] - f.pi[s];
  double* ls = lx + f.px[s];
  std::fill(ls, ls + nscol * nsrow, 0.0);
  for (long e = a_start_[static_cast<size_t>(s)]; e < a_start_[static_cast<size_t>(s) + 1]; ++e) {
    lx[a_dest_[static_cast<size_t>(e)]] = values[a_src_[static_cast<size_t>(e)]];
  }
}

// Columns [c0, c1) of supernode s lose every descendant's update to them, in increasing order of the descendant:
// c = L_d(rows from q1) L_d(rows q1..q2)^T (syrk on the square, gemm below it), subtracted where map puts its rows.
void TreeCholesky::ApplyUpdates(const SupernodalFactor& f, int s, int c0, int c1, const int* map, double* c, double* lx) const {
  const int* super = f.super;
  const int* pi = f.pi;
  const int k1 = super[s];
  const int nsrow = pi[s + 1] - pi[s];
  double* ls = lx + f.px[s];
  const double one = 1.0, zero = 0.0;
  for (long u = u_start_[static_cast<size_t>(s)]; u < u_start_[static_cast<size_t>(s) + 1]; ++u) {
    const Update& up = updates_[static_cast<size_t>(u)];
    const int d = up.d;
    const int ndcol = super[d + 1] - super[d], ndrow = pi[d + 1] - pi[d];
    const int* drows = f.rows + pi[d];
    const int q1 = static_cast<int>(std::lower_bound(drows + up.p1, drows + up.p2, k1 + c0) - drows);
    const int q2 = static_cast<int>(std::lower_bound(drows + q1, drows + up.p2, k1 + c1) - drows);
    if (q1 == q2) continue;
    const int m = ndrow - q1, k = q2 - q1;
    const double* a1 = lx + f.px[d] + q1;
    dsyrk_("L", "N", &k, &ndcol, &one, a1, &ndrow, &zero, c, &m);
    if (m > k) {
      const int rest = m - k;
      dgemm_("N", "T", &rest, &k, &ndcol, &one, a1 + k, &ndrow, a1, &ndrow, &zero, c + k, &m);
    }
    for (int jj = 0; jj < k; ++jj) {
      double* lcol = ls + static_cast<long>(drows[q1 + jj] - k1) * nsrow;
      const double* cc = c + static_cast<long>(jj) * m;
      for (int ii = jj; ii < m; ++ii) lcol[map[drows[q1 + ii]]] -= cc[ii];
    }
  }
}

// The diagonal block's Cholesky, then the rows below: L21 = A21 L11^-T (in two halves of the rows when split).
bool TreeCholesky::Finish(const SupernodalFactor& f, int s, double* lx, bool split_rows) const {
  const int nscol = f.super[s + 1] - f.super[s];
  const int nsrow = f.pi[s + 1] - f.pi[s], below = nsrow - nscol;
  double* ls = lx + f.px[s];
  int info = 0;
  dpotrf_("L", &nscol, ls, &nsrow, &info);
  if (info != 0) return false;
  if (below == 0) return true;
  const double one = 1.0;
  const auto solve = [&](int r0, int r1) {
    const int count = r1 - r0;
    dtrsm_("R", "L", "T", "N", &count, &nscol, &one, ls, &nsrow, ls + nscol + r0, &nsrow);
  };
  if (split_rows && below >= 16) {
    const int half = below / 2;
    tbb::parallel_invoke([&] { solve(0, half); }, [&] { solve(half, below); });
  } else {
    solve(0, below);
  }
  return true;
}

bool TreeCholesky::FactorNode(const SupernodalFactor& f, int s, const double* values, double* lx, int* map, double* c) const {
  const int nsrow = f.pi[s + 1] - f.pi[s];
  const int* srows = f.rows + f.pi[s];
  for (int p = 0; p < nsrow; ++p) map[srows[p]] = p;
  Assemble(f, s, values, lx);
  ApplyUpdates(f, s, 0, f.super[s + 1] - f.super[s], map, c, lx);
  return Finish(f, s, lx, false);
}

bool TreeCholesky::Factorize(const SupernodalFactor& f, const double* values, double* lx, Workspace* workspace) const {
  if (f.n != n_ || f.nsuper != nsuper_) return false;
  for (int b = 0; b < 2; ++b) {
    workspace->map[b].resize(static_cast<size_t>(f.n));
    workspace->c[b].resize(c_size_);
  }
  // The bins' subtrees at once (either stops at the other's failure: the answer is "not positive definite" then).
  std::atomic<bool> failed{false};
  const auto bin = [&](int b) {
    for (const auto& [first, end] : split_.bins[b]) {
      for (int s = first; s < end; ++s) {
        if (failed.load(std::memory_order_relaxed)) return;
        if (!FactorNode(f, s, values, lx, workspace->map[b].data(), workspace->c[b].data())) {
          failed.store(true, std::memory_order_relaxed);
          return;
        }
      }
    }
  };
  tbb::parallel_invoke([&] { bin(0); }, [&] { bin(1); });
  if (failed.load()) return false;
  // The top, in order; a wide supernode's updates split by columns between the threads.
  int* map = workspace->map[0].data();
  for (int s : split_.top) {
    const int nscol = f.super[s + 1] - f.super[s];
    const int nsrow = f.pi[s + 1] - f.pi[s];
    const int* srows = f.rows + f.pi[s];
    for (int p = 0; p < nsrow; ++p) map[srows[p]] = p;
    Assemble(f, s, values, lx);
    const bool wide = wide_[static_cast<size_t>(s)] != 0;
    if (wide) {
      const int half = nscol / 2;
      tbb::parallel_invoke([&] { ApplyUpdates(f, s, 0, half, map, workspace->c[0].data(), lx); },
                           [&] { ApplyUpdates(f, s, half, nscol, map, workspace->c[1].data(), lx); });
    } else {
      ApplyUpdates(f, s, 0, nscol, map, workspace->c[0].data(), lx);
    }
    if (!Finish(f, s, lx, wide)) return false;
  }
  return true;
}

}  // namespace springblend::internal
