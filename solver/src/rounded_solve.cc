#include "rounded_solve.h"

#include <algorithm>
#include <cstddef>
#include <cstring>

#include <tbb/parallel_invoke.h>

#include "supernodal_tree.h"

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

// Forward, the diagonal block of supernode s: y_j /= L_jj, and the block's rows below j lose L_rj y_j.
SPRINGBLEND_INLINE void ForwardDiagonal(const SupernodalFactor& factor, int s, double* y) {
  const int k1 = factor.super[s], nscol = factor.super[s + 1] - k1;
  const int nsrow = factor.pi[s + 1] - factor.pi[s];
  const float* ls = factor.values + factor.px[s];
  for (int j = 0; j < nscol; ++j) {
    const float* col = Column(ls, j, nsrow);
    const double yj = y[k1 + j] / col[j];
    y[k1 + j] = yj;
    for (int r = j + 1; r < nscol; ++r) y[k1 + r] -= col[r] * yj;
  }
}

// Forward, rows [r0, r1) below the diagonal block of supernode s: w = L21 y1 there, four columns at a time (w is read
// and written once per four), then the rows lose it: from y, or summed into acc where top_row marks the row (a
// bin's updates to the tree's top). Each row's sum is the same whatever the range, so halves give the same bits.
SPRINGBLEND_INLINE void ForwardBelow(const SupernodalFactor& factor, int s, int r0, int r1, double* y, double* w,
                                     const char* top_row, double* acc) {
  const int k1 = factor.super[s], nscol = factor.super[s + 1] - k1;
  const int nsrow = factor.pi[s + 1] - factor.pi[s];
  const float* ls = factor.values + factor.px[s];
  std::fill(w + r0, w + r1, 0.0);
  int j = 0;
  for (; j + 4 <= nscol; j += 4) {
    const float* c0 = Column(ls, j, nsrow) + nscol;
    const float* c1 = c0 + nsrow;
    const float* c2 = c1 + nsrow;
    const float* c3 = c2 + nsrow;
    const double y0 = y[k1 + j], y1 = y[k1 + j + 1], y2 = y[k1 + j + 2], y3 = y[k1 + j + 3];
    int r = r0;
    for (; r + kLanes <= r1; r += kLanes) {
      const Doubles sum = (Load8(c0 + r) * y0 + Load8(c1 + r) * y1) + (Load8(c2 + r) * y2 + Load8(c3 + r) * y3);
      const Doubles wr = LoadDoubles(w + r) + sum;
      std::memcpy(w + r, &wr, sizeof wr);
    }
    for (; r < r1; ++r) w[r] += (c0[r] * y0 + c1[r] * y1) + (c2[r] * y2 + c3[r] * y3);
  }
  for (; j < nscol; ++j) {
    const float* c = Column(ls, j, nsrow) + nscol;
    const double yj = y[k1 + j];
    for (int r = r0; r < r1; ++r) w[r] += c[r] * yj;
  }
  const int* srows = factor.rows + factor.pi[s] + nscol;
  if (top_row == nullptr) {
    for (int r = r0; r < r1; ++r) y[srows[r]] -= w[r];
  } else {
    for (int r = r0; r < r1; ++r) {
      const int row = srows[r];
      if (top_row[row]) {
        acc[row] += w[r];
      } else {
        y[row] -= w[r];
      }
    }
  }
}

SPRINGBLEND_INLINE void ForwardRange(const SupernodalFactor& factor, int first, int end, double* y, double* w,
                                     const char* top_row, double* acc) {
  for (int s = first; s < end; ++s) {
    ForwardDiagonal(factor, s, y);
    const int below = (factor.pi[s + 1] - factor.pi[s]) - (factor.super[s + 1] - factor.super[s]);
    if (below > 0) ForwardBelow(factor, s, 0, below, y, w, top_row, acc);
  }
}

// Backward, t_j = sum_r L_rj w_r over the rows below supernode s's diagonal block (w: y at those rows), for columns
// [j0, j1), four at a time (w is read once per four); j0 a multiple of four, so halves give the same bits.
SPRINGBLEND_INLINE void BackwardBelow(const SupernodalFactor& factor, int s, int j0, int j1, const double* w,
                                      double* t) {
  const int nscol = factor.super[s + 1] - factor.super[s];
  const int nsrow = factor.pi[s + 1] - factor.pi[s], below = nsrow - nscol;
  const float* ls = factor.values + factor.px[s];
  int j = j0;
  for (; j + 4 <= j1; j += 4) {
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
  for (; j < j1; ++j) t[j] = Dot(Column(ls, j, nsrow) + nscol, w, below);
}

SPRINGBLEND_INLINE void BackwardGather(const SupernodalFactor& factor, int s, const double* y, double* w) {
  const int nscol = factor.super[s + 1] - factor.super[s];
  const int below = (factor.pi[s + 1] - factor.pi[s]) - nscol;
  const int* srows = factor.rows + factor.pi[s] + nscol;
  for (int r = 0; r < below; ++r) w[r] = y[srows[r]];
}

// Backward, the diagonal block: y_j = (y_j - t_j - sum_r L_rj y_r over the block's rows below j) / L_jj.
SPRINGBLEND_INLINE void BackwardDiagonal(const SupernodalFactor& factor, int s, double* y, const double* t) {
  const int k1 = factor.super[s], nscol = factor.super[s + 1] - k1;
  const int nsrow = factor.pi[s + 1] - factor.pi[s];
  const float* ls = factor.values + factor.px[s];
  for (int j = nscol - 1; j >= 0; --j) {
    const float* col = Column(ls, j, nsrow);
    y[k1 + j] = (y[k1 + j] - (t[j] + Dot(col + j + 1, y + k1 + j + 1, nscol - j - 1))) / col[j];
  }
}

// Supernodes end - 1 down to first: the rows below first (t), then the diagonal block.
SPRINGBLEND_INLINE void BackwardRange(const SupernodalFactor& factor, int first, int end, double* y, double* w,
                                      double* t) {
  for (int s = end - 1; s >= first; --s) {
    const int nscol = factor.super[s + 1] - factor.super[s];
    const int below = (factor.pi[s + 1] - factor.pi[s]) - nscol;
    std::fill(t, t + nscol, 0.0);
    if (below > 0) {
      BackwardGather(factor, s, y, w);
      BackwardBelow(factor, s, 0, nscol, w, t);
    }
    BackwardDiagonal(factor, s, y, t);
  }
}

// The kernels once per instruction set.
struct Kernels {
  void (*forward_range)(const SupernodalFactor&, int, int, double*, double*, const char*, double*);
  void (*forward_diagonal)(const SupernodalFactor&, int, double*);
  void (*forward_below)(const SupernodalFactor&, int, int, int, double*, double*, const char*, double*);
  void (*backward_range)(const SupernodalFactor&, int, int, double*, double*, double*);
  void (*backward_below)(const SupernodalFactor&, int, int, int, const double*, double*);
  void (*backward_diagonal)(const SupernodalFactor&, int, double*, const double*);
};

#define SPRINGBLEND_KERNELS(NAME, TARGET)                                                                            \
  TARGET void NAME##ForwardRange(const SupernodalFactor& f, int a, int b, double* y, double* w, const char* top,  \
                                 double* acc) {                                                                  \
    ForwardRange(f, a, b, y, w, top, acc);                                                                       \
  }                                                                                                              \
  TARGET void NAME##ForwardDiagonal(const SupernodalFactor& f, int s, double* y) { ForwardDiagonal(f, s, y); }   \
  TARGET void NAME##ForwardBelow(const SupernodalFactor& f, int s, int r0, int r1, double* y, double* w,         \
                                 const char* top, double* acc) {                                                 \
    ForwardBelow(f, s, r0, r1, y, w, top, acc);                                                                  \
  }                                                                                                              \
  TARGET void NAME##BackwardRange(const SupernodalFactor& f, int a, int b, double* y, double* w, double* t) {    \
    BackwardRange(f, a, b, y, w, t);                                                                             \
  }                                                                                                              \
  TARGET void NAME##BackwardBelow(const SupernodalFactor& f, int s, int j0, int j1, const double* w, double* t) { \
    BackwardBelow(f, s, j0, j1, w, t);                                                                           \
  }                                                                                                              \
  TARGET void NAME##BackwardDiagonal(const SupernodalFactor& f, int s, double* y, const double* t) {             \
    BackwardDiagonal(f, s, y, t);                                                                                \
  }                                                                                                              \
  constexpr Kernels k##NAME = {NAME##ForwardRange,  NAME##ForwardDiagonal, NAME##ForwardBelow,                   \
                               NAME##BackwardRange, NAME##BackwardBelow,   NAME##BackwardDiagonal};

SPRINGBLEND_KERNELS(Generic, )
SPRINGBLEND_KERNELS(Avx2, __attribute__((target("avx2"))))
SPRINGBLEND_KERNELS(Avx512, __attribute__((target("avx512f"))))
#undef SPRINGBLEND_KERNELS

const Kernels& KernelsFor(KernelIsa isa) {
  switch (isa) {
    case KernelIsa::kAvx512:
      if (__builtin_cpu_supports("avx512f")) return kAvx512;
      break;
    case KernelIsa::kAvx2:
      if (__builtin_cpu_supports("avx2")) return kAvx2;
      break;
    case KernelIsa::kGeneric:
      break;
  }
  return kGeneric;
}

// A supernode's entries the solve reads: the lower triangle of its diagonal block and the rows below.
long NodeEntries(const SupernodalFactor& factor, int s) {
  const long nscol = factor.super[s + 1] - factor.super[s];
  const long below = (factor.pi[s + 1] - factor.pi[s]) - nscol;
  return nscol * (nscol + 1) / 2 + below * nscol;
}

// A top supernode is split between the two threads when its part below the diagonal has at least this many entries
// (a split costs a task's hand-over, a few microseconds; this many floats take about that long to stream).
constexpr long kSplitEntries = 16384;

void ForwardTop(const Kernels& k, const SupernodalFactor& factor, int s, double* y, double* w) {
  k.forward_diagonal(factor, s, y);
  const int nscol = factor.super[s + 1] - factor.super[s];
  const int below = (factor.pi[s + 1] - factor.pi[s]) - nscol;
  if (below <= 0) return;
  if (static_cast<long>(below) * nscol < kSplitEntries || below < 2 * kLanes) {
    k.forward_below(factor, s, 0, below, y, w, nullptr, nullptr);
    return;
  }
  const int half = below / 2 / kLanes * kLanes;
  tbb::parallel_invoke([&] { k.forward_below(factor, s, 0, half, y, w, nullptr, nullptr); },
                       [&] { k.forward_below(factor, s, half, below, y, w, nullptr, nullptr); });
}

void BackwardTop(const Kernels& k, const SupernodalFactor& factor, int s, double* y, double* w, double* t) {
  const int nscol = factor.super[s + 1] - factor.super[s];
  const int below = (factor.pi[s + 1] - factor.pi[s]) - nscol;
  std::fill(t, t + nscol, 0.0);
  if (below > 0) {
    BackwardGather(factor, s, y, w);
    if (static_cast<long>(below) * nscol < kSplitEntries || nscol < 8) {
      k.backward_below(factor, s, 0, nscol, w, t);
    } else {
      const int half = nscol / 2 / 4 * 4;
      tbb::parallel_invoke([&] { k.backward_below(factor, s, 0, half, w, t); },
                           [&] { k.backward_below(factor, s, half, nscol, w, t); });
    }
  }
  k.backward_diagonal(factor, s, y, t);
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

SolveSchedule PlanSolve(const SupernodalFactor& factor) {
  SolveSchedule plan;
  // Work: the entries a supernode's solve reads; at the top its rows below are split between the threads.
  std::vector<double> own(static_cast<size_t>(factor.nsuper)), shared(static_cast<size_t>(factor.nsuper));
  for (int s = 0; s < factor.nsuper; ++s) {
    const long nscol = factor.super[s + 1] - factor.super[s];
    const long diagonal = nscol * (nscol + 1) / 2;
    own[static_cast<size_t>(s)] = static_cast<double>(NodeEntries(factor, s));
    shared[static_cast<size_t>(s)] = static_cast<double>(diagonal) + 0.5 * static_cast<double>(NodeEntries(factor, s) - diagonal);
    plan.entries += NodeEntries(factor, s);
  }
  TreeSplit split = SplitTree(factor, own, shared);
  if (!split.parallel) return plan;
  plan.parallel = true;
  plan.top = std::move(split.top);
  for (int b = 0; b < 2; ++b) {
    plan.bins[b] = std::move(split.bins[b]);
    plan.bin_entries[b] = static_cast<long>(split.bin_work[b]);
  }
  plan.top_entries = static_cast<long>(split.top_work);
  plan.top_row.assign(static_cast<size_t>(factor.n), 0);
  for (int s : plan.top) {
    for (int k = factor.super[s]; k < factor.super[s + 1]; ++k) {
      plan.top_row[static_cast<size_t>(k)] = 1;
      plan.top_rows.push_back(k);
    }
  }
  return plan;
}

void SolveWorkspace::Fit(const SupernodalFactor& factor, int max_below) {
  const size_t n = static_cast<size_t>(factor.n);
  const size_t rows = static_cast<size_t>(std::max(max_below, 1));
  const size_t columns = static_cast<size_t>(MaxSupernodeColumns(factor));
  y.resize(n);
  for (int b = 0; b < 2; ++b) {
    w[b].resize(rows);
    t[b].resize(columns);
    acc[b].resize(n);
  }
}

void RoundedSupernodalSolve(const SupernodalFactor& factor, const SolveSchedule* schedule, const double* b,
                            double* x, SolveWorkspace* workspace, KernelIsa isa) {
  const Kernels& k = KernelsFor(isa);
  const int n = factor.n;
  double* y = workspace->y.data();
  double* w0 = workspace->w[0].data();
  double* t0 = workspace->t[0].data();
  for (int i = 0; i < n; ++i) y[i] = b[factor.perm[i]];
  if (schedule == nullptr || !schedule->parallel) {
    k.forward_range(factor, 0, factor.nsuper, y, w0, nullptr, nullptr);
    k.backward_range(factor, 0, factor.nsuper, y, w0, t0);
  } else {
    // Forward: the two bins at once, their updates to the top's rows summed apart; then the top.
    double* acc[2] = {workspace->acc[0].data(), workspace->acc[1].data()};
    for (int row : schedule->top_rows) acc[0][row] = acc[1][row] = 0.0;
    const char* top_row = schedule->top_row.data();
    auto forward_bin = [&](int bin) {
      for (const auto& [first, end] : schedule->bins[bin]) {
        k.forward_range(factor, first, end, y, workspace->w[bin].data(), top_row, acc[bin]);
      }
    };
    tbb::parallel_invoke([&] { forward_bin(0); }, [&] { forward_bin(1); });
    for (int row : schedule->top_rows) y[row] = (y[row] - acc[0][row]) - acc[1][row];
    for (int s : schedule->top) ForwardTop(k, factor, s, y, w0);
    // Backward: the top, then the two bins at once (each reads the top's rows and writes its own).
    for (auto s = schedule->top.rbegin(); s != schedule->top.rend(); ++s) BackwardTop(k, factor, *s, y, w0, t0);
    auto backward_bin = [&](int bin) {
      const auto& ranges = schedule->bins[bin];
      for (auto range = ranges.rbegin(); range != ranges.rend(); ++range) {
        k.backward_range(factor, range->first, range->second, y, workspace->w[bin].data(),
                         workspace->t[bin].data());
      }
    };
    tbb::parallel_invoke([&] { backward_bin(0); }, [&] { backward_bin(1); });
  }
  for (int i = 0; i < n; ++i) x[factor.perm[i]] = y[i];
}

}  // namespace springblend::internal
