#include "hessian_pattern.h"

#include <algorithm>

namespace springblend::internal {

HessianPattern HessianPattern::Build(int vertices, const std::vector<int>& a,
                                     const std::vector<int>& b) {
  const int springs = static_cast<int>(a.size());
  // For every vertex j, the springs (i, j) with i < j, sorted by i: they give the rows above the
  // diagonal block in the three columns of j.
  std::vector<int> lower_count(vertices + 1, 0);
  for (int q = 0; q < springs; ++q) ++lower_count[b[q] + 1];
  for (int v = 0; v < vertices; ++v) lower_count[v + 1] += lower_count[v];
  std::vector<int> lower(springs);
  {
    std::vector<int> fill(lower_count.begin(), lower_count.end() - 1);
    for (int q = 0; q < springs; ++q) lower[fill[b[q]]++] = q;
  }
  for (int v = 0; v < vertices; ++v) {
    std::sort(lower.begin() + lower_count[v], lower.begin() + lower_count[v + 1],
              [&](int p, int q) { return a[p] < a[q]; });
  }

  HessianPattern out;
  out.spring_slots.resize(springs);
  out.vertex_slots.resize(vertices);
  SymmetricPattern& m = out.matrix;
  m.n = 3 * vertices;
  m.column_starts.assign(m.n + 1, 0);
  m.row_indices.reserve(static_cast<size_t>(9) * springs + static_cast<size_t>(6) * vertices);
  for (int j = 0; j < vertices; ++j) {
    for (int cj = 0; cj < 3; ++cj) {
      const int column = 3 * j + cj;
      m.column_starts[column] = static_cast<int>(m.row_indices.size());
      for (int k = lower_count[j]; k < lower_count[j + 1]; ++k) {
        const int q = lower[k];
        for (int ci = 0; ci < 3; ++ci) {
          out.spring_slots[q][ci * 3 + cj] = static_cast<int>(m.row_indices.size());
          m.row_indices.push_back(3 * a[q] + ci);
        }
      }
      for (int ci = 0; ci <= cj; ++ci) {
        // Upper-triangle index of (ci, cj) in the order (0,0) (0,1) (0,2) (1,1) (1,2) (2,2).
        const int upper = ci == 0 ? cj : (ci == 1 ? 2 + cj : 5);
        out.vertex_slots[j][upper] = static_cast<int>(m.row_indices.size());
        m.row_indices.push_back(3 * j + ci);
      }
    }
  }
  m.column_starts[m.n] = static_cast<int>(m.row_indices.size());
  return out;
}

}  // namespace springblend::internal
