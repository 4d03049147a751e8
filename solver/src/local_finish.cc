#include "local_finish.h"

#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>

#include "hessian_pattern.h"
#include "line_search.h"
#include "sparse_cholesky.h"

namespace springblend::internal {

namespace {

// A diagonal block's upper triangle: (0,0) (0,1) (0,2) (1,1) (1,2) (2,2), as HessianPattern::vertex_slots.
constexpr int kRow[6] = {0, 0, 0, 1, 1, 2};
constexpr int kCol[6] = {0, 1, 2, 1, 2, 2};

// Newton on the free coordinates of the region's vertices, everything else held where it is.
class RegionNewton {
 public:
  RegionNewton(SpringSystem* springs, const std::vector<char>& held, double shift, double diagonal,
               double mean_rest_length, const LocalFinishOptions& options, const std::function<bool()>* stop,
               LocalFinishResult* result)
      : springs_(*springs),
        topology_(springs->topology()),
        held_(held),
        shift_(shift),
        diagonal_(diagonal),
        max_move_(options.max_step_fraction * mean_rest_length),
        tiny_(1e-12 * mean_rest_length),
        options_(options),
        stop_(stop),
        result_(*result),
        index_(3 * static_cast<size_t>(topology_.vertices), -1),
        spring_marked_(static_cast<size_t>(topology_.springs()), 0) {}

  // Makes the region's unknowns and springs, and its Hessian's pattern: the rig's full pattern restricted to
  // the region's unknowns, and where each spring's and each vertex's block land in it (so an assembly writes
  // in place, with no triplets to sort).
  void SetRegion(const std::vector<int>& region) {
    for (int d : coordinates_) index_[d] = -1;
    for (int q : springs_in_) spring_marked_[q] = 0;
    coordinates_.clear();
    springs_in_.clear();
    for (int v : region) {
      for (int c = 0; c < 3; ++c) {
        const int d = 3 * v + c;
        if (held_[d]) continue;
        index_[d] = static_cast<int>(coordinates_.size());
        coordinates_.push_back(d);
      }
      for (int e = topology_.vertex_spring_offsets[v]; e < topology_.vertex_spring_offsets[v + 1]; ++e) {
        const int q = topology_.vertex_springs[e];
        if (!spring_marked_[q]) {
          spring_marked_[q] = 1;
          springs_in_.push_back(q);
        }
      }
    }
    std::sort(springs_in_.begin(), springs_in_.end());  // a fixed summation order
    // Upper triangle by columns; the region's unknowns ascend with the full ones, so rows stay sorted.
    const SymmetricPattern& full = topology_.pattern->matrix;
    pattern_.n = static_cast<int>(coordinates_.size());
    pattern_.column_starts.clear();
    pattern_.row_indices.clear();
    diagonal_entries_.clear();
    for (int j = 0; j < pattern_.n; ++j) {
      const int d = coordinates_[j];
      pattern_.column_starts.push_back(static_cast<int>(pattern_.row_indices.size()));
      for (int k = full.column_starts[d]; k < full.column_starts[d + 1]; ++k) {
        const int i = index_[full.row_indices[k]];
        if (i < 0) continue;
        if (i == j) diagonal_entries_.push_back(static_cast<int>(pattern_.row_indices.size()));
        pattern_.row_indices.push_back(i);
      }
    }
    pattern_.column_starts.push_back(static_cast<int>(pattern_.row_indices.size()));
    values_.resize(pattern_.row_indices.size());
    // Where each spring's block and each vertex's diagonal block land among the region's entries (-1: a
    // coordinate outside the region or held).
    const auto entry = [&](int row, int column) {
      const int i = index_[row], j = index_[column];
      if (i < 0 || j < 0) return -1;
      const auto first = pattern_.row_indices.begin() + pattern_.column_starts[j];
      const auto last = pattern_.row_indices.begin() + pattern_.column_starts[j + 1];
      return static_cast<int>(std::lower_bound(first, last, i) - pattern_.row_indices.begin());
    };
    spring_entries_.resize(springs_in_.size());
    for (size_t e = 0; e < springs_in_.size(); ++e) {
      const int q = springs_in_[e];
      const int a = topology_.a[q], b = topology_.b[q];  // a < b: block (a, b) is in the upper triangle
      for (int ci = 0; ci < 3; ++ci) {
        for (int cj = 0; cj < 3; ++cj) spring_entries_[e][ci * 3 + cj] = entry(3 * a + ci, 3 * b + cj);
      }
    }
    vertex_entries_.resize(region.size());
    vertex_block_starts_.assign(1, 0);
    vertex_blocks_.clear();
    for (size_t r = 0; r < region.size(); ++r) {
      for (int i = 0; i < 6; ++i) vertex_entries_[r][i] = entry(3 * region[r] + kRow[i], 3 * region[r] + kCol[i]);
      // Its springs' places in springs_in_ (every spring of a region vertex is there), in the full assembly's
      // order.
      const int v = region[r];
      for (int e = topology_.vertex_spring_offsets[v]; e < topology_.vertex_spring_offsets[v + 1]; ++e) {
        const auto at = std::lower_bound(springs_in_.begin(), springs_in_.end(), topology_.vertex_springs[e]);
        vertex_blocks_.push_back(static_cast<int>(at - springs_in_.begin()));
      }
      vertex_block_starts_.push_back(static_cast<int>(vertex_blocks_.size()));
    }
    analysed_ = false;
  }

  // Newton until the region is in balance with a short last step. False when it cannot get there.
  bool Run(Eigen::VectorXd* x, double* last_step) {
    const int m = static_cast<int>(coordinates_.size());
    Eigen::VectorXd force(m), step(m), trial_force(m);
    Eigen::VectorXd& positions = *x;
    Eigen::VectorXd trial = positions;
    double residual = Force(positions, &force);
    double energy = Energy(positions);
    *last_step = 0.0;
    for (;;) {
      if (!std::isfinite(residual) || !std::isfinite(energy)) {
        result_.why = "non-finite force or energy";
        return false;
      }
      if (residual <= options_.residual_tolerance && *last_step <= options_.step_tolerance * diagonal_) return true;
      if (result_.iterations >= options_.max_iterations) {
        result_.why = "no convergence in the region";
        return false;
      }
      if (stop_ != nullptr && *stop_ && (*stop_)()) {
        result_.why = "cancelled";
        return false;
      }
      ++result_.iterations;
      if (!Direction(positions, force, &step)) {
        result_.why = "no factorization of the region's Hessian";
        return false;
      }
      // The longest move of one vertex (its up to three free coordinates) is clamped, as in a full solve.
      double longest = 0.0;
      for (int i = 0; i < m;) {
        const int v = coordinates_[i] / 3;
        double sq = 0.0;
        while (i < m && coordinates_[i] / 3 == v) sq += step[i] * step[i], ++i;
        longest = std::max(longest, std::sqrt(sq));
      }
      if (longest > max_move_) step *= max_move_ / longest;
      LineSearchOptions search;
      search.max_steps = options_.max_line_search_steps;
      const LineSearchResult found = BacktrackingLineSearch(
          energy, -force.dot(step), residual, search,
          [&](double t) {
            for (int i = 0; i < m; ++i) trial[coordinates_[i]] = positions[coordinates_[i]] + t * step[i];
            return Energy(trial);
          },
          [&] { return Force(trial, &trial_force); });
      result_.line_search_halvings += found.halvings;
      if (!found.accepted) {
        for (int i = 0; i < m; ++i) trial[coordinates_[i]] = positions[coordinates_[i]];
        if (residual <= options_.residual_tolerance) return true;  // in balance; the step check could not finish
        result_.why = "the line search found no lower energy in the region";
        return false;
      }
      for (int i = 0; i < m; ++i) positions[coordinates_[i]] = trial[coordinates_[i]];
      energy = found.energy;
      residual = Force(positions, &force);
      *last_step = found.step * step.lpNorm<Eigen::Infinity>();
    }
  }

 private:
  double Energy(const Eigen::VectorXd& x) const {
    const std::vector<double>& k = springs_.stiffness();
    const std::vector<double>& r = springs_.rest_lengths();
    double sum = 0.0;
    for (int q : springs_in_) {
      const double l = (x.segment<3>(3 * topology_.a[q]) - x.segment<3>(3 * topology_.b[q])).norm();
      sum += 0.5 * k[q] * (l - r[q]) * (l - r[q]);
    }
    return sum;
  }

  // Forces on the region's unknowns; returns the largest.
  double Force(const Eigen::VectorXd& x, Eigen::VectorXd* force) const {
    const std::vector<double>& k = springs_.stiffness();
    const std::vector<double>& r = springs_.rest_lengths();
    force->setZero(static_cast<Eigen::Index>(coordinates_.size()));
    for (int q : springs_in_) {
      const int a = topology_.a[q], b = topology_.b[q];
      const Eigen::Vector3d d = x.segment<3>(3 * a) - x.segment<3>(3 * b);
      const double l = d.norm();
      if (l <= tiny_) continue;
      const Eigen::Vector3d fa = (-k[q] * (l - r[q]) / l) * d;
      for (int c = 0; c < 3; ++c) {
        if (const int i = index_[3 * a + c]; i >= 0) (*force)[i] += fa[c];
        if (const int i = index_[3 * b + c]; i >= 0) (*force)[i] -= fa[c];
      }
    }
    return force->size() == 0 ? 0.0 : force->lpNorm<Eigen::Infinity>();
  }

  // The region's Hessian values (pattern_'s layout): each spring's block at its entries, each region vertex's
  // diagonal block summed from its springs (in the order the full assembly sums them).
  void Assemble(const Eigen::VectorXd& x, double negative_scale, double extra_shift) {
    const std::vector<double>& k = springs_.stiffness();
    const std::vector<double>& r = springs_.rest_lengths();
    std::fill(values_.begin(), values_.end(), 0.0);
    blocks_.resize(springs_in_.size());
    for (size_t e = 0; e < springs_in_.size(); ++e) {
      const int q = springs_in_[e];
      const Eigen::Vector3d d = x.segment<3>(3 * topology_.a[q]) - x.segment<3>(3 * topology_.b[q]);
      const double l = d.norm();
      Eigen::Matrix3d& h = blocks_[e];
      if (l <= tiny_) {
        h = k[q] * Eigen::Matrix3d::Identity();
      } else {
        const Eigen::Vector3d u = d / l;
        double s = 1.0 - r[q] / l;
        if (s < 0.0) s *= negative_scale;
        h = k[q] * ((1.0 - s) * (u * u.transpose()) + s * Eigen::Matrix3d::Identity());
      }
      for (int i = 0; i < 9; ++i) {
        if (const int at = spring_entries_[e][i]; at >= 0) values_[at] = -h(i / 3, i % 3);
      }
    }
    for (size_t v = 0; v < vertex_entries_.size(); ++v) {
      Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
      for (int e = vertex_block_starts_[v]; e < vertex_block_starts_[v + 1]; ++e) h += blocks_[vertex_blocks_[e]];
      for (int i = 0; i < 6; ++i) {
        if (const int at = vertex_entries_[v][i]; at >= 0) values_[at] = h(kRow[i], kCol[i]);
      }
    }
    for (int e : diagonal_entries_) values_[e] += shift_ + extra_shift;
  }

  // The Newton step H step = force: the true Hessian while its Cholesky succeeds, else the projected one
  // (compressed springs' transverse curvature clamped at zero), else that with a small shift.
  bool Direction(const Eigen::VectorXd& x, const Eigen::VectorXd& force, Eigen::VectorXd* step) {
    for (int attempt = 0; attempt < 3; ++attempt) {
      Assemble(x, attempt == 0 ? 1.0 : 0.0, attempt == 2 ? 1e-8 * MeanDiagonal() : 0.0);
      if (!analysed_) {
        cholesky_ = SparseCholesky::Create(options_.linear_solver);
        cholesky_->Analyze(pattern_);
        analysed_ = true;
      }
      const FactorStatus status = cholesky_->Factorize(values_.data());
      ++result_.factorizations;
      if (attempt > 0) ++result_.projected_factorizations;
      if (status == FactorStatus::kOk) {
        step->resize(force.size());
        cholesky_->Solve(force.data(), step->data());
        if (step->allFinite()) return true;
      }
    }
    return false;
  }

  double MeanDiagonal() const {
    double sum = 0.0;
    for (int e : diagonal_entries_) sum += std::abs(values_[e]);
    return diagonal_entries_.empty() ? 1.0 : sum / static_cast<double>(diagonal_entries_.size());
  }

  SpringSystem& springs_;
  const SpringTopology& topology_;
  const std::vector<char>& held_;
  double shift_, diagonal_, max_move_, tiny_;
  const LocalFinishOptions& options_;
  const std::function<bool()>* stop_;
  LocalFinishResult& result_;
  std::vector<int> index_;        // per coordinate: its unknown in the region, or -1
  std::vector<int> coordinates_;  // the region's unknowns, ascending
  std::vector<char> spring_marked_;
  std::vector<int> springs_in_;   // springs with an endpoint in the region
  SymmetricPattern pattern_;      // the region's, analysed by cholesky_ (which keeps a pointer to it)
  std::vector<std::array<int, 9>> spring_entries_;  // per spring of springs_in_: block (a, b)'s entries, or -1
  std::vector<std::array<int, 6>> vertex_entries_;  // per region vertex: its diagonal block's upper triangle
  std::vector<int> vertex_block_starts_, vertex_blocks_;  // per region vertex: its springs' indices in springs_in_
  std::vector<int> diagonal_entries_;
  std::vector<double> values_;    // pattern_'s values
  std::vector<Eigen::Matrix3d> blocks_;  // per spring of springs_in_: its Hessian block
  std::unique_ptr<SparseCholesky> cholesky_;
  bool analysed_ = false;
};

}  // namespace

LocalFinishResult LocalFinish(SpringSystem* springs, const std::vector<char>& held, double diagonal_shift,
                              double diagonal, double mean_rest_length, const LocalFinishOptions& options,
                              const std::function<bool()>* stop, Eigen::VectorXd* x) {
  LocalFinishResult result;
  const SpringTopology& topology = springs->topology();
  const int n = topology.vertices;
  const Curvature curvature{1.0, false};
  std::vector<char> movable(n, 0);
  for (int v = 0; v < n; ++v) {
    movable[v] = !(held[3 * v] && held[3 * v + 1] && held[3 * v + 2]);
    result.free_vertices += movable[v];
  }
  double residual = springs->Evaluate(*x, held, curvature, false);
  result.initial_residual = residual;
  result.residual = residual;
  if (residual <= options.residual_tolerance) {
    result.converged = true;
    return result;
  }
  const auto out_of_balance = [&](int v) {
    const Eigen::VectorXd& f = springs->force();
    for (int c = 0; c < 3; ++c) {
      if (std::abs(f[3 * v + c]) > options.residual_tolerance) return true;
    }
    return false;
  };
  std::vector<char> in_region(n, 0);
  std::vector<int> region;
  // Adds the seeds and `rings` rings of neighbours (through any spring) to the region.
  const auto grow = [&](std::vector<int> front, int rings) {
    std::vector<char> seen(n, 0);
    for (int v : front) seen[v] = 1;
    for (int ring = 0; ring <= rings; ++ring) {
      std::vector<int> next;
      for (int v : front) {
        if (movable[v] && !in_region[v]) {
          in_region[v] = 1;
          region.push_back(v);
        }
        if (ring == rings) continue;
        for (int e = topology.vertex_spring_offsets[v]; e < topology.vertex_spring_offsets[v + 1]; ++e) {
          const int q = topology.vertex_springs[e];
          const int w = topology.a[q] == v ? topology.b[q] : topology.a[q];
          if (!seen[w]) {
            seen[w] = 1;
            next.push_back(w);
          }
        }
      }
      front = std::move(next);
    }
    std::sort(region.begin(), region.end());
  };
  std::vector<int> seeds;
  for (int v = 0; v < n; ++v) {
    if (movable[v] && out_of_balance(v)) seeds.push_back(v);
  }
  if (seeds.size() > options.max_seed_share * result.free_vertices) {
    result.why = "out of balance at too many vertices to start";
    return result;
  }
  grow(seeds, 1);
  RegionNewton newton(springs, held, diagonal_shift, diagonal, mean_rest_length, options, stop, &result);
  for (;;) {
    result.vertices = static_cast<int>(region.size());
    if (region.size() > options.max_share * result.free_vertices) {
      result.why = "the region outgrew its share of the vertices";
      break;
    }
    ++result.rounds;
    newton.SetRegion(region);
    double last_step = 0.0;
    const bool ok = newton.Run(x, &last_step);
    residual = springs->Evaluate(*x, held, curvature, false);
    result.residual = residual;
    result.last_step = last_step / diagonal;
    if (!ok) break;
    if (residual <= options.residual_tolerance && last_step <= options.step_tolerance * diagonal) {
      result.converged = true;
      break;
    }
    seeds.clear();
    for (int v = 0; v < n; ++v) {
      if (movable[v] && !in_region[v] && out_of_balance(v)) seeds.push_back(v);
    }
    if (seeds.empty()) {
      result.why = "out of balance inside the region after its solve";
      break;
    }
    if (result.rounds >= options.max_rounds) {
      result.why = "the region kept growing";
      break;
    }
    // One ring after the first round, then twice as many each round: where a solve's imbalance crossed the
    // region's edge once it reaches further the next time (soft parts near the rest shape or a target). On the
    // face's jawOpen and the horse's paths (bench/paths_bench.cc, 17 frames each, one run each on 2026-12-07):
    // path frames 5.4 and 6.1 ms median, 151 and 237 ms at most, against 5.5 and 7.4 ms, 215 and 254 ms with two
    // rings every round (the maxima are full solves after a local finish gave up).
    grow(seeds, 1 << (result.rounds - 1));
  }
  return result;
}

}  // namespace springblend::internal
