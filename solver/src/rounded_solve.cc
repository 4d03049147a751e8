#include "rounded_solve.h"

#include <algorithm>
#include <cstddef>

namespace springblend::internal {
namespace {

// Two-lane sums in a fixed order (deterministic, and vectorized without reassociating).
typedef double Pair __attribute__((vector_size(16)));

// Column j of a supernode's entries (nsrow of them per column) from `first`.
const float* Column(const float* first, int j, int nsrow) { return first + static_cast<std::ptrdiff_t>(j) * nsrow; }

// sum_r c[r] v[r] over count entries.
double Dot(const float* c, const double* v, int count) {
  Pair acc = {0.0, 0.0};
  int r = 0;
  for (; r + 2 <= count; r += 2) acc += Pair{c[r], c[r + 1]} * Pair{v[r], v[r + 1]};
  double sum = acc[0] + acc[1];
  if (r < count) sum += c[r] * v[r];
  return sum;
}

}  // namespace

void RoundedSupernodalSolve(const SupernodalFactor& factor, const double* b, double* x, double* y, double* w) {
  const int n = factor.n;
  const int* perm = factor.perm;
  const int* super = factor.super;
  const int* pi = factor.pi;
  const int* px = factor.px;
  const int* rows = factor.rows;
  const float* lx = factor.values;
  for (int k = 0; k < n; ++k) y[k] = b[perm[k]];
  const int nsuper = factor.nsuper;
  for (int s = 0; s < nsuper; ++s) {
    const int k1 = super[s], nscol = super[s + 1] - k1;
    const int nsrow = pi[s + 1] - pi[s], below = nsrow - nscol;
    const float* ls = lx + px[s];
    // The diagonal block: y1 = L11^{-1} y1.
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
      for (int r = 0; r < below; ++r) w[r] += (c0[r] * y0 + c1[r] * y1) + (c2[r] * y2 + c3[r] * y3);
    }
    for (; j < nscol; ++j) {
      const float* c = Column(ls, j, nsrow) + nscol;
      const double yj = y[k1 + j];
      for (int r = 0; r < below; ++r) w[r] += c[r] * yj;
    }
    const int* srows = rows + pi[s] + nscol;
    for (int r = 0; r < below; ++r) y[srows[r]] -= w[r];
  }
  for (int s = nsuper - 1; s >= 0; --s) {
    const int k1 = super[s], nscol = super[s + 1] - k1;
    const int nsrow = pi[s + 1] - pi[s], below = nsrow - nscol;
    const float* ls = lx + px[s];
    const int* srows = rows + pi[s] + nscol;
    // y1 -= L21^T w, w = y at the rows below (four columns at a time: w is read once per four).
    if (below > 0) {
      for (int r = 0; r < below; ++r) w[r] = y[srows[r]];
      int j = 0;
      for (; j + 4 <= nscol; j += 4) {
        const float* c0 = Column(ls, j, nsrow) + nscol;
        const float* c1 = c0 + nsrow;
        const float* c2 = c1 + nsrow;
        const float* c3 = c2 + nsrow;
        Pair a0 = {0.0, 0.0}, a1 = a0, a2 = a0, a3 = a0;
        int r = 0;
        for (; r + 2 <= below; r += 2) {
          const Pair wv = {w[r], w[r + 1]};
          a0 += Pair{c0[r], c0[r + 1]} * wv;
          a1 += Pair{c1[r], c1[r + 1]} * wv;
          a2 += Pair{c2[r], c2[r + 1]} * wv;
          a3 += Pair{c3[r], c3[r + 1]} * wv;
        }
        double t0 = a0[0] + a0[1], t1 = a1[0] + a1[1], t2 = a2[0] + a2[1], t3 = a3[0] + a3[1];
        if (r < below) {
          t0 += c0[r] * w[r];
          t1 += c1[r] * w[r];
          t2 += c2[r] * w[r];
          t3 += c3[r] * w[r];
        }
        y[k1 + j] -= t0;
        y[k1 + j + 1] -= t1;
        y[k1 + j + 2] -= t2;
        y[k1 + j + 3] -= t3;
      }
      for (; j < nscol; ++j) y[k1 + j] -= Dot(Column(ls, j, nsrow) + nscol, w, below);
    }
    // The diagonal block: y1 = L11^{-T} y1.
    for (int j = nscol - 1; j >= 0; --j) {
      const float* col = Column(ls, j, nsrow);
      y[k1 + j] = (y[k1 + j] - Dot(col + j + 1, y + k1 + j + 1, nscol - j - 1)) / col[j];
    }
  }
  for (int k = 0; k < n; ++k) x[perm[k]] = y[k];
}

}  // namespace springblend::internal
