#include "rounded_solve.h"

#include <algorithm>
#include <cstddef>
#include <cstring>

// Every sum has a fixed order: eight lanes (GCC's generic vectors, which the compiler splits into what the machine
// has) summed pairwise at the end, then the tail. The kernels are compiled for AVX-512, AVX2 and plain x86-64 (the
// best the machine has is used), with floating-point contraction off (solver/CMakeLists.txt), so each does the same
// operations in the same order: the same answer on every machine.
// Everything a kernel calls is inlined into each instruction set's copy, and so compiled for it.
#define SPRINGBLEND_INLINE __attribute__((always_inline)) inline

namespace springblend::internal {
namespace {

typedef double Doubles __attribute__((vector_size(64)));
typedef float Floats __attribute__((vector_size(32)));
constexpr int kLanes = 8;


// Eight entries from p, as doubles.
SPRINGBLEND_INLINE Doubles Load8(const float* p) {
  Floats f;
  std::memcpy(&f, p, sizeof f);
  return __builtin_convertvector(f, Doubles);
}
SPRINGBLEND_INLINE Doubles LoadDoubles(const double* p) {
  Doubles d;
  std::memcpy(&d, p, sizeof d);
  return d;
}

SPRINGBLEND_INLINE double Sum(Doubles a) { return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7])); }

// sum_r c[r] v[r] over count entries.
SPRINGBLEND_INLINE double Dot(const float* c, const double* v, int count) {
  Doubles acc = {};
  int r = 0;
  for (; r + kLanes <= count; r += kLanes) acc += Load8(c + r) * LoadDoubles(v + r);
  double sum = Sum(acc);
  for (; r < count; ++r) sum += c[r] * v[r];
  return sum;
}

// Column j of a supernode's entries (nsrow of them per column) from `first`.
SPRINGBLEND_INLINE const float* Column(const float* first, int j, int nsrow) {
  return first + static_cast<std::ptrdiff_t>(j) * nsrow;
}

SPRINGBLEND_INLINE void Solve(const SupernodalFactor& factor, const double* b, double* x, double* y, double* w,
                              double* t) {
  const int n = factor.n;
  const int* perm = factor.perm;
  const int* super = factor.super;
  const int* pi = factor.pi;
  const int* px = factor.px;
  const int* rows = factor.rows;
  const float* lx = factor.values;
  for (int k = 0; k < n; ++k) y[k] = b[perm[k]];
  const int nsuper = factor.nsuper;
  // Forward, L y = P b. Column j: y_j /= L_jj, and the rows below lose L_rj y_j.
  for (int s = 0; s < nsuper; ++s) {
    const int k1 = super[s], nscol = super[s + 1] - k1;
    const int nsrow = pi[s + 1] - pi[s], below = nsrow - nscol;
    const float* ls = lx + px[s];
    for (int j = 0; j < nscol; ++j) {
      const float* col = Column(ls, j, nsrow);
      const double yj = y[k1 + j] / col[j];
      y[k1 + j] = yj;
      for (int r = j + 1; r < nscol; ++r) y[k1 + r] -= col[r] * yj;
    }
    if (below == 0) continue;
    // w = L21 y1, four columns at a time (w is read and written once per four).
    std::fill(w, w + below, 0.0);
    int j = 0;
    for (; j + 4 <= nscol; j += 4) {
      const float* c0 = Column(ls, j, nsrow) + nscol;
      const float* c1 = c0 + nsrow;
      const float* c2 = c1 + nsrow;
      const float* c3 = c2 + nsrow;
      const double y0 = y[k1 + j], y1 = y[k1 + j + 1], y2 = y[k1 + j + 2], y3 = y[k1 + j + 3];
      int r = 0;
      for (; r + kLanes <= below; r += kLanes) {
        const Doubles sum = (Load8(c0 + r) * y0 + Load8(c1 + r) * y1) + (Load8(c2 + r) * y2 + Load8(c3 + r) * y3);
        const Doubles wr = LoadDoubles(w + r) + sum;
        std::memcpy(w + r, &wr, sizeof wr);
      }
      for (; r < below; ++r) w[r] += (c0[r] * y0 + c1[r] * y1) + (c2[r] * y2 + c3[r] * y3);
    }
    for (; j < nscol; ++j) {
      const float* c = Column(ls, j, nsrow) + nscol;
      const double yj = y[k1 + j];
      for (int r = 0; r < below; ++r) w[r] += c[r] * yj;
    }
    const int* srows = rows + pi[s] + nscol;
    for (int r = 0; r < below; ++r) y[srows[r]] -= w[r];
  }
  // Backward, L^T x = y. Column j: y_j = (y_j - sum_r L_rj y_r) / L_jj, the rows below first (t_j, four columns at
  // a time: w, the values at the rows below, is read once per four), then the diagonal block.
  for (int s = nsuper - 1; s >= 0; --s) {
    const int k1 = super[s], nscol = super[s + 1] - k1;
    const int nsrow = pi[s + 1] - pi[s], below = nsrow - nscol;
    const float* ls = lx + px[s];
    const int* srows = rows + pi[s] + nscol;
    std::fill(t, t + nscol, 0.0);
    if (below > 0) {
      for (int r = 0; r < below; ++r) w[r] = y[srows[r]];
      int j = 0;
      for (; j + 4 <= nscol; j += 4) {
        const float* c0 = Column(ls, j, nsrow) + nscol;
        const float* c1 = c0 + nsrow;
        const float* c2 = c1 + nsrow;
        const float* c3 = c2 + nsrow;
        Doubles a0 = {}, a1 = {}, a2 = {}, a3 = {};
        int r = 0;
        for (; r + kLanes <= below; r += kLanes) {
          const Doubles wv = LoadDoubles(w + r);
          a0 += Load8(c0 + r) * wv;
          a1 += Load8(c1 + r) * wv;
          a2 += Load8(c2 + r) * wv;
          a3 += Load8(c3 + r) * wv;
        }
        double t0 = Sum(a0), t1 = Sum(a1), t2 = Sum(a2), t3 = Sum(a3);
        for (; r < below; ++r) {
          t0 += c0[r] * w[r];
          t1 += c1[r] * w[r];
          t2 += c2[r] * w[r];
          t3 += c3[r] * w[r];
        }
        t[j] = t0;
        t[j + 1] = t1;
        t[j + 2] = t2;
        t[j + 3] = t3;
      }
      for (; j < nscol; ++j) t[j] = Dot(Column(ls, j, nsrow) + nscol, w, below);
    }
    for (int j = nscol - 1; j >= 0; --j) {
      const float* col = Column(ls, j, nsrow);
      y[k1 + j] = (y[k1 + j] - (t[j] + Dot(col + j + 1, y + k1 + j + 1, nscol - j - 1))) / col[j];
    }
  }
  for (int k = 0; k < n; ++k) x[perm[k]] = y[k];
}

// The kernel once per instruction set.
void SolveGeneric(const SupernodalFactor& factor, const double* b, double* x, double* y, double* w, double* t) {
  Solve(factor, b, x, y, w, t);
}
__attribute__((target("avx2"))) void SolveAvx2(const SupernodalFactor& factor, const double* b, double* x, double* y,
                                               double* w, double* t) {
  Solve(factor, b, x, y, w, t);
}
__attribute__((target("avx512f"))) void SolveAvx512(const SupernodalFactor& factor, const double* b, double* x,
                                                    double* y, double* w, double* t) {
  Solve(factor, b, x, y, w, t);
}

}  // namespace

KernelIsa BestKernelIsa() {
  if (__builtin_cpu_supports("avx512f")) return KernelIsa::kAvx512;
  if (__builtin_cpu_supports("avx2")) return KernelIsa::kAvx2;
  return KernelIsa::kGeneric;
}

int MaxSupernodeColumns(const SupernodalFactor& factor) {
  int most = 1;
  for (int s = 0; s < factor.nsuper; ++s) most = std::max(most, factor.super[s + 1] - factor.super[s]);
  return most;
}

void RoundedSupernodalSolve(const SupernodalFactor& factor, const double* b, double* x, double* y, double* w,
                            double* t, KernelIsa isa) {
  switch (isa) {
    case KernelIsa::kAvx512:
      if (__builtin_cpu_supports("avx512f")) return SolveAvx512(factor, b, x, y, w, t);
      break;
    case KernelIsa::kAvx2:
      if (__builtin_cpu_supports("avx2")) return SolveAvx2(factor, b, x, y, w, t);
      break;
    case KernelIsa::kGeneric:
      break;
  }
  SolveGeneric(factor, b, x, y, w, t);
}

}  // namespace springblend::internal
