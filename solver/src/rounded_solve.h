// The triangular solves with a supernodal Cholesky factor (CHOLMOD's layout) whose entries are rounded to single
// precision: the conjugate gradients' preconditioner. Its own file so that sanitizer builds can leave it
// uninstrumented (solver/CMakeLists.txt): it streams the factor at the memory's speed, and checking each load
// made the ASan stage several times slower. Its answers are checked by the linear system's tests.
#pragma once

#include <utility>
#include <vector>

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

// How a solve is shared between two threads, from the factor's structure alone (its elimination tree), so the
// answer never depends on how many threads run it. The tree's top (`top`: the supernodes nearest the root, in
// increasing order) is solved by both threads together, each big supernode split into two halves of its rows
// (forward) or columns (backward), which gives the same bits as one thread; the subtrees below it are dealt into two
// bins of about equal work, solved at the same time. A bin's updates to the top's rows are summed apart
// (`top_row` marks those rows) and added in a fixed order, bin 0 then bin 1. `parallel` is false where the
// tree has no two subtrees worth sharing (or is not postordered): then the plain sequential solve runs.
struct SolveSchedule {
  bool parallel = false;
  std::vector<int> top;
  std::vector<std::pair<int, int>> bins[2];  // supernode ranges [first, end), increasing
  std::vector<char> top_row;                 // n flags
  std::vector<int> top_rows;
  long entries = 0;                          // the factor's entries the solve reads (lower triangles of blocks)
  long top_entries = 0;
  long bin_entries[2] = {0, 0};
};
SolveSchedule PlanSolve(const SupernodalFactor& factor);

// A solve's workspace, sized by Fit for a factor.
struct SolveWorkspace {
  std::vector<double> y, w[2], t[2], acc[2];
  void Fit(const SupernodalFactor& factor, int max_below);
};

// x = P^T L^{-T} L^{-1} P b. L's entries are read as floats and every sum is in double, in a fixed order (the
// same answer on every run, machine and thread count). With a schedule (PlanSolve), two threads of the caller's
// TBB arena share it where the tree allows; without one, it runs in one thread. max_below of Fit: the largest number
// of rows below a supernode's diagonal block (CHOLMOD's maxesize).
void RoundedSupernodalSolve(const SupernodalFactor& factor, const SolveSchedule* schedule, const double* b,
                            double* x, SolveWorkspace* workspace, KernelIsa isa = BestKernelIsa());

// The most columns of a supernode.
int MaxSupernodeColumns(const SupernodalFactor& factor);

}  // namespace springblend::internal
