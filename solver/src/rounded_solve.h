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

// The instruction sets the kernels below are compiled for. Each gives the same answer to the bit (same operations in
// the same order, no fused multiply-adds); a machine uses the best it has, and a kernel asked for one the machine
// lacks runs the generic one.
enum class KernelIsa { kGeneric, kAvx2, kAvx512 };
KernelIsa BestKernelIsa();

// x = P^T L^{-T} L^{-1} P b. L's entries are read as floats and every sum is in double, in a fixed order (the
// same answer on every run and machine). y: n doubles of workspace; w: at least the largest number of rows
// below a supernode's diagonal block (1 if none); t: at least the most columns of a supernode.
void RoundedSupernodalSolve(const SupernodalFactor& factor, const double* b, double* x, double* y, double* w,
                            double* t, KernelIsa isa = BestKernelIsa());

// The most columns of a supernode (t's size above).
int MaxSupernodeColumns(const SupernodalFactor& factor);

}  // namespace springblend::internal
