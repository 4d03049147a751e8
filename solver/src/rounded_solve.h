// The triangular solves with a supernodal Cholesky factor (CHOLMOD's layout) whose entries are rounded to single
// precision: the conjugate gradients' preconditioner. Its own file so that sanitizer builds can leave it
// uninstrumented (solver/CMakeLists.txt): it streams the factor at the memory's speed, and checking each load
// made the ASan stage several times slower. Its answers are checked by the linear system's tests.
#pragma once

namespace springblend::internal {

// A supernodal factor L (L L^T = P A P^T) as CHOLMOD lays it out: supernode s holds columns super[s] ..
// super[s + 1] - 1, its row indices rows[pi[s] .. pi[s + 1]) (the diagonal block's first), and its entries
// column by column from values[px[s]].
struct SupernodalFactor {
  int n = 0;
  int nsuper = 0;
  const int* perm = nullptr;
  const int* super = nullptr;
  const int* pi = nullptr;
  const int* px = nullptr;
  const int* rows = nullptr;
  const float* values = nullptr;
};

// x = P^T L^{-T} L^{-1} P b. L's entries are read as floats and every sum is in double, in a fixed order (the
// same answer on every run and machine). y: n doubles of workspace; w: at least the largest number of rows
// below a supernode's diagonal block (1 if none).
void RoundedSupernodalSolve(const SupernodalFactor& factor, const double* b, double* x, double* y, double* w);

}  // namespace springblend::internal
