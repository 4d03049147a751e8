// How a supernodal factor's elimination tree is shared between two threads: its top (the supernodes nearest the
// root), worked on by both threads together, and its subtrees below the top dealt into two bins of about equal
// work, one per thread. Computed from the factor's structure and a work estimate alone, never from the threads
// that run it, so what runs (and so every answer's bits) is the same with one thread or two.
#pragma once

#include <utility>
#include <vector>

#include "rounded_solve.h"

namespace springblend::internal {

struct TreeSplit {
  bool parallel = false;  // false where the tree has no two subtrees worth sharing or is not postordered
  std::vector<int> top;   // increasing
  std::vector<std::pair<int, int>> bins[2];  // supernode ranges [first, end), increasing: whole subtrees
  double top_work = 0.0;
  double bin_work[2] = {0.0, 0.0};
};

// parent[s] of each supernode (the supernode holding its first row below the diagonal block; -1 for a root), or
// an empty vector where a parent does not come after its child (the tree is not postordered).
std::vector<int> SupernodeParents(const SupernodalFactor& structure);

// own[s]: a supernode's work when a bin's thread does it alone; shared[s]: its time when both threads do it
// together at the top. The top is opened from the roots (the largest subtree's root moved to the top, its
// children made subtrees) while that lowers the estimate max(bins) + sum of the top's shared; ties go to the lower
// supernode.
TreeSplit SplitTree(const SupernodalFactor& structure, const std::vector<double>& own,
                    const std::vector<double>& shared);

}  // namespace springblend::internal
