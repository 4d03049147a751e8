#include "supernodal_tree.h"

#include <algorithm>
#include <cstddef>

namespace springblend::internal {

std::vector<int> SupernodeParents(const SupernodalFactor& structure) {
  const int nsuper = structure.nsuper;
  std::vector<int> node_of(static_cast<size_t>(structure.n), -1);
  for (int s = 0; s < nsuper; ++s) {
    for (int k = structure.super[s]; k < structure.super[s + 1]; ++k) node_of[static_cast<size_t>(k)] = s;
  }
  std::vector<int> parent(static_cast<size_t>(nsuper), -1);
  for (int s = 0; s < nsuper; ++s) {
    const int nscol = structure.super[s + 1] - structure.super[s];
    int p = -1;
    for (int k = structure.pi[s] + nscol; k < structure.pi[s + 1]; ++k) {
      const int node = node_of[static_cast<size_t>(structure.rows[k])];
      if (p < 0 || node < p) p = node;
    }
    if (p >= 0 && p <= s) return {};
    parent[static_cast<size_t>(s)] = p;
  }
  return parent;
}

TreeSplit SplitTree(const SupernodalFactor& structure, const std::vector<double>& own,
                    const std::vector<double>& shared) {
  TreeSplit split;
  const int nsuper = structure.nsuper;
  const std::vector<int> parent = SupernodeParents(structure);
  if (parent.empty()) return split;
  std::vector<int> size(static_cast<size_t>(nsuper), 1);
  std::vector<double> work(own);
  std::vector<std::vector<int>> children(static_cast<size_t>(nsuper));
  std::vector<int> candidates;
  double total = 0.0;
  for (int s = 0; s < nsuper; ++s) {
    total += own[static_cast<size_t>(s)];
    const int p = parent[static_cast<size_t>(s)];
    if (p < 0) {
      candidates.push_back(s);
      continue;
    }
    work[static_cast<size_t>(p)] += work[static_cast<size_t>(s)];
    size[static_cast<size_t>(p)] += size[static_cast<size_t>(s)];
    children[static_cast<size_t>(p)].push_back(s);
  }
  // Subtree s must be the range [s - size + 1, s] (postorder).
  for (int s = 0; s < nsuper; ++s) {
    const int first = s - size[static_cast<size_t>(s)] + 1;
    for (int c : children[static_cast<size_t>(s)]) {
      if (c - size[static_cast<size_t>(c)] + 1 < first) return split;
    }
  }
  const auto heavier = [&](int a, int b) {
    return work[static_cast<size_t>(a)] != work[static_cast<size_t>(b)]
               ? work[static_cast<size_t>(a)] > work[static_cast<size_t>(b)]
               : a < b;
  };
  // Largest subtrees first, each to the lighter bin (bin 0 on a tie).
  const auto deal = [&](const std::vector<int>& subtrees, std::vector<int> bins[2], double load[2]) {
    std::vector<int> order = subtrees;
    std::sort(order.begin(), order.end(), heavier);
    load[0] = load[1] = 0.0;
    for (int c : order) {
      const int bin = load[1] < load[0] ? 1 : 0;
      load[bin] += work[static_cast<size_t>(c)];
      bins[bin].push_back(c);
    }
  };
  double best = total, top_cost = 0.0;
  std::vector<int> top, best_top, best_candidates;
  for (int round = 0; round < 4096 && !candidates.empty() && top_cost < best; ++round) {
    std::vector<int> bins[2];
    double load[2];
    deal(candidates, bins, load);
    const double estimate = std::max(load[0], load[1]) + top_cost;
    if (!bins[1].empty() && estimate < best) {
      best = estimate;
      best_top = top;
      best_candidates = candidates;
    }
    const auto largest = std::min_element(candidates.begin(), candidates.end(), heavier);
    const int open = *largest;
    candidates.erase(largest);
    top.push_back(open);
    top_cost += shared[static_cast<size_t>(open)];
    for (int c : children[static_cast<size_t>(open)]) candidates.push_back(c);
  }
  if (best_candidates.empty()) return split;
  split.parallel = true;
  split.top = best_top;
  std::sort(split.top.begin(), split.top.end());
  for (int s : split.top) split.top_work += own[static_cast<size_t>(s)];
  std::vector<int> bins[2];
  double load[2];
  deal(best_candidates, bins, load);
  for (int b = 0; b < 2; ++b) {
    std::sort(bins[b].begin(), bins[b].end());
    for (int c : bins[b]) split.bins[b].push_back({c - size[static_cast<size_t>(c)] + 1, c + 1});
    split.bin_work[b] = load[b];
  }
  return split;
}

}  // namespace springblend::internal
