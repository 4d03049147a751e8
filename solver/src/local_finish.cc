#include "local_finish.h"

#include <Eigen/Dense>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <cmath>

#include "line_search.h"
#include "sparse_cholesky.h"

namespace springblend::internal {

namespace {

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

  // Makes the region's unknowns and springs. `region`: vertices with a free coordinate.
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

  void Assemble(const Eigen::VectorXd& x, double negative_scale, double extra_shift) {
    const std::vector<double>& k = springs_.stiffness();
    const std::vector<double>& r = springs_.rest_lengths();
    triplets_.clear();
    const auto add = [&](int row, int col, double value) {
      const int i = index_[row], j = index_[col];
      if (i >= 0 && j >= 0 && i >= j) triplets_.emplace_back(i, j, value);
    };
    for (int q : springs_in_) {
      const int a = topology_.a[q], b = topology_.b[q];
      const Eigen::Vector3d d = x.segment<3>(3 * a) - x.segment<3>(3 * b);
      const double l = d.norm();
      Eigen::Matrix3d h;
      if (l <= tiny_) {
        h = k[q] * Eigen::Matrix3d::Identity();
      } else {
        const Eigen::Vector3d u = d / l;
        double s = 1.0 - r[q] / l;
        if (s < 0.0) s *= negative_scale;
        h = k[q] * ((1.0 - s) * (u * u.transpose()) + s * Eigen::Matrix3d::Identity());
      }
      for (int ci = 0; ci < 3; ++ci) {
        for (int cj = 0; cj < 3; ++cj) {
          add(3 * a + ci, 3 * a + cj, h(ci, cj));
          add(3 * b + ci, 3 * b + cj, h(ci, cj));
          add(3 * a + ci, 3 * b + cj, -h(ci, cj));
          add(3 * b + ci, 3 * a + cj, -h(ci, cj));
        }
      }
    }
    const int m = static_cast<int>(coordinates_.size());
    for (int i = 0; i < m; ++i) triplets_.emplace_back(i, i, shift_ + extra_shift);
    matrix_.resize(m, m);
    matrix_.setFromTriplets(triplets_.begin(), triplets_.end());
  }

  // The Newton step H step = force: the true Hessian while its Cholesky succeeds, else the projected one
  // (compressed springs' transverse curvature clamped at zero), else that with a small shift.
  bool Direction(const Eigen::VectorXd& x, const Eigen::VectorXd& force, Eigen::VectorXd* step) {
    for (int attempt = 0; attempt < 3; ++attempt) {
      Assemble(x, attempt == 0 ? 1.0 : 0.0, attempt == 2 ? 1e-8 * MeanDiagonal() : 0.0);
      if (!analysed_ || matrix_.nonZeros() != static_cast<Eigen::Index>(pattern_.row_indices.size())) {
        pattern_.n = static_cast<int>(matrix_.rows());
        pattern_.column_starts.assign(matrix_.outerIndexPtr(), matrix_.outerIndexPtr() + matrix_.rows() + 1);
        pattern_.row_indices.assign(matrix_.innerIndexPtr(), matrix_.innerIndexPtr() + matrix_.nonZeros());
        cholesky_ = SparseCholesky::Create(options_.linear_solver);
        cholesky_->Analyze(pattern_);
        analysed_ = true;
      }
      const FactorStatus status = cholesky_->Factorize(matrix_.valuePtr());
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
    for (int i = 0; i < matrix_.rows(); ++i) sum += std::abs(matrix_.coeff(i, i));
    return matrix_.rows() > 0 ? sum / static_cast<double>(matrix_.rows()) : 1.0;
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
  std::vector<Eigen::Triplet<double>> triplets_;
  // The lower triangle stored by rows, which is the upper one by columns: the backend's layout (SymmetricPattern).
  Eigen::SparseMatrix<double, Eigen::RowMajor> matrix_;
  SymmetricPattern pattern_;  // the region's, analysed by cholesky_ (which keeps a pointer to it)
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
    grow(seeds, 2);
  }
  return result;
}

}  // namespace springblend::internal
