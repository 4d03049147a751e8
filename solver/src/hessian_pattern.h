// The fixed sparsity pattern of the spring system's Hessian and a slot map into its value array, so the
// per-iteration assembly writes values in place with no triplet sorting (method.md section 4).
#pragma once

#include <array>
#include <vector>

#include "sparse_cholesky.h"

namespace springblend::internal {

struct HessianPattern {
  SymmetricPattern matrix;  // 3 * vertices unknowns, x/y/z of vertex i at 3i..3i+2
  // For spring q (a < b): the 9 value slots of block (a, b), row-major over (component of a, of b).
  std::vector<std::array<int, 9>> spring_slots;
  // For vertex v: the 6 value slots of the upper triangle of diagonal block (v, v):
  // (0,0) (0,1) (0,2) (1,1) (1,2) (2,2).
  std::vector<std::array<int, 6>> vertex_slots;

  // Builds the pattern of a system with `vertices` vertices and springs (a[q], b[q]), a[q] < b[q], at
  // most one spring per vertex pair.
  static HessianPattern Build(int vertices, const std::vector<int>& a, const std::vector<int>& b);
};

}  // namespace springblend::internal
