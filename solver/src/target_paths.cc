// The target paths' build (target_paths.h): each target's sweeps assembled into its path, whose samples are
// kept and intervals certified within the cap, the targets in parallel; and the paths' sizes.
#include "target_paths.h"

#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_arena.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <mutex>

#include "path_internals.h"
#include "path_sweep.h"
#include "rig_internals.h"
#include "springblend/error.h"

namespace springblend::internal {

namespace {

// Newton iterations a midpoint check may take: from an interpolant within the tolerance of its equilibrium,
// Newton converges in one to three; a check that needs more is not within it, whatever it would converge to.
// On the face's jawOpen path (bench/paths_bench.cc): checks 199 Newton and 1393 CG iterations against 321 and
// 2081 with 6, the build 55 s against 62 s, 35 uncertified intervals against 50, 7 of 17 frames finished
// locally against 5.
constexpr int kCheckIterations = 3;
constexpr std::uint8_t kUnchecked = 255;
// Solved steps at multiples of 1 / kKeptGrid are always kept.
constexpr double kKeptGrid = 8.0;

// Work run by TBB inside a group that another task's exception cancelled (another target's path that was
// stopped) is skipped without an exception of its own: what it should have filled is empty, so stop too.
void ThrowIfCancelled() {
  if (tbb::is_current_task_group_canceling()) ThrowCancelled();
}

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

PathField CorrectionField(const Sample& s) { return PathField(s.correction, s.two_words ? 2 : 1); }
PathField TangentField(const Sample& s) { return s.tangent.size() > 0 ? PathField(s.tangent) : PathField(); }

// Largest distance of a vertex between two corrections.
double Distance(const Eigen::MatrixXd& a, const Eigen::MatrixXd& b) {
  return std::sqrt((a - b).rowwise().squaredNorm().maxCoeff());
}

void BuildPath(const Rig& rig, int target, const TargetPathsOptions& options, TargetPath* path) {
  const auto start = std::chrono::steady_clock::now();
  // Two chains of solves, each with its own solver (whose kept factorization carries from one solve to the
  // next and preconditions the next solve while it stays close): the sweeps inside [0, 1] on one, the
  // extensions on the other; the midpoint checks split between them. Each chain is sequential and its work
  // fixed, so the paths do not depend on the threads.
  PathSolver solver(rig, target, options.tolerance, options.stop);
  PathSolver side(rig, target, options.tolerance, options.stop);
  const double diagonal = rig.summary().bounding_box_diagonal;
  const double h = 1.0 / options.intervals;
  // The knots of [0, 1]: the rest shape, the target's in-betweens and the target, each the sculpted shape of
  // its weight (an equilibrium of zero energy, unless a mask changed it).
  std::vector<double> knots = {0.0};
  for (const auto& knot : rig.internals().controls.targets[target]) knots.push_back(knot.weight);
  std::vector<double> kinks(knots.begin() + 1, knots.end() - 1);  // the in-betweens: the path may bend there
  // A chain solved downwards: sample j was solved coming from sample j - 1 (or the knot above, `top`), so a
  // fold found by sample j lies below its predecessor.
  const auto mark_descending = [](std::vector<Sample>& chain, Sample* top) {
    for (size_t j = 0; j < chain.size(); ++j) {
      if (chain[j].jumped) (j == 0 ? *top : chain[j - 1]).fold_before = true;
    }
  };
  // Per segment between two knots: the sweep up from the lower knot; where it does not end on the upper
  // knot's shape, the sweep down from that too while its energy is the lower one, and one switch from the up
  // branch to the down branch where that run ends.
  std::vector<Sample> inside;
  std::vector<int> switches;  // in `inside`: intervals from an up branch to a down branch
  Sample rest = solver.End(0.0);
  const Sample full = solver.End(1.0);
  const auto sweep_inside = [&] {
    Sample lower = rest;
    for (size_t j = 0; j + 1 < knots.size(); ++j) {
      const double a = knots[j], b = knots[j + 1];
      const int steps = std::max(1, static_cast<int>(std::ceil((b - a) / h - 1e-9)));
      std::vector<double> grid;
      for (int k = 0; k <= steps; ++k) grid.push_back(k == steps ? b : a + (b - a) * k / steps);
      std::vector<Sample> up;
      Continuation from_lower;
      from_lower.Add(lower);
      up.push_back(std::move(lower));
      for (size_t k = 1; k < grid.size(); ++k) solver.Refined(grid[k - 1], grid[k], from_lower, &up);
      for (size_t k = 1; k < up.size(); ++k) up[k].fold_before = up[k].jumped;
      Sample upper = j + 2 == knots.size() ? full : solver.End(b);
      if (up.back().converged &&
          Distance(upper.correction, up.back().correction) <= options.tolerance * diagonal) {
        upper.fold_before = up.back().fold_before;
        up.pop_back();
        inside.insert(inside.end(), std::make_move_iterator(up.begin()), std::make_move_iterator(up.end()));
        lower = std::move(upper);
        continue;
      }
      std::vector<Sample> down;  // descending
      const auto energy_at = [](const std::vector<Sample>& samples, double alpha) {
        for (const Sample& s : samples) {
          if (s.alpha == alpha) return s.energy;
        }
        return std::numeric_limits<double>::infinity();
      };
      // The sweep down goes on while its branch has the lower energy at the grid's points: the path follows it
      // from the upper knot down to the last such point, and the up branch below (one switch, decided per
      // interval). The steps below that point would not be kept, so they are not solved.
      double switch_at = b;
      Continuation from_upper;
      from_upper.Add(upper);
      for (size_t k = grid.size() - 1; k-- > 1;) {
        const size_t before = down.size();
        solver.Refined(grid[k + 1], grid[k], from_upper, &down);
        if (!(energy_at(down, grid[k]) < energy_at(up, grid[k]))) {
          down.resize(before);  // this step (and its halvings) lies below the switch
          break;
        }
        switch_at = grid[k];
      }
      mark_descending(down, &upper);
      std::reverse(down.begin(), down.end());  // ascending, above a
      for (Sample& s : up) {
        if (s.alpha < switch_at) inside.push_back(std::move(s));
      }
      switches.push_back(static_cast<int>(inside.size()) - 1);
      for (Sample& s : down) {
        if (s.alpha >= switch_at) inside.push_back(std::move(s));
      }
      lower = std::move(upper);
    }
    inside.push_back(std::move(lower));  // the target
  };
  // Beyond [0, 1]: continuation from the ends.
  const int beyond = static_cast<int>(std::ceil(options.extension * options.intervals - 1e-9));
  std::vector<Sample> above, below;  // below: descending
  Sample rest_mark;                  // a fold between the rest shape and the first sample below it
  const auto sweep_beyond = [&] {
    {
      Continuation predictor;
      predictor.Add(full);
      for (int k = 1; k <= beyond; ++k) side.Refined(1.0 + (k - 1) * h, 1.0 + k * h, predictor, &above);
      for (Sample& s : above) s.fold_before = s.jumped;
    }
    Continuation predictor;
    predictor.Add(rest);
    for (int k = 1; k <= beyond; ++k) side.Refined(-(k - 1) * h, -k * h, predictor, &below);
    mark_descending(below, &rest_mark);
  };
  tbb::parallel_invoke(sweep_inside, sweep_beyond);
  ThrowIfCancelled();
  inside.front().fold_before = rest_mark.fold_before;
  // The dense path: every sample the sweeps solved.
  std::vector<Sample> dense(std::make_move_iterator(below.rbegin()), std::make_move_iterator(below.rend()));
  const int first_inside = static_cast<int>(dense.size());
  dense.insert(dense.end(), std::make_move_iterator(inside.begin()), std::make_move_iterator(inside.end()));
  dense.insert(dense.end(), std::make_move_iterator(above.begin()), std::make_move_iterator(above.end()));
  const int n_dense = static_cast<int>(dense.size());
  for (const Sample& s : dense) {
    if (!s.converged) ++path->unconverged;
  }
  // Per dense interval: a switch between branches, a fold, or smooth.
  std::vector<std::uint8_t> dense_kind(n_dense - 1, kUnchecked);
  for (int i : switches) dense_kind[first_inside + i] = kSwitch;
  for (int k = 1; k < n_dense; ++k) {
    if (dense[k].fold_before && dense_kind[k - 1] != kSwitch) dense_kind[k - 1] = kFold;
  }
  std::vector<std::uint8_t> dense_break(n_dense, 0);
  for (int k = 0; k < n_dense; ++k) {
    for (double w : kinks) dense_break[k] |= dense[k].alpha == w ? 1 : 0;
  }

  // The kept samples: at first the ends, the knots, both sides of every switch and fold (where the path is
  // not smooth), the steps on a grid of kKeptGrid per unit (so a frame at such a weight starts at its answer,
  // whatever the tolerance) and then every other step, as far as the cap allows (on the face's jawOpen path,
  // keeping every step against the grid alone: path frames 59 against 125 ms median, 12 of 17 finished
  // locally against 8, the build 31 against 35 s); then, as long as an interval's interpolant
  // misses a dense sample inside it by more than the tolerance, the dense sample nearest its midpoint joins
  // (no solve needed). An interval with no dense sample inside is checked at its midpoint against an
  // equilibrium solved there from the interpolant, and split by that equilibrium while the check fails and
  // halving pays.
  std::vector<int> dense_of;  // per kept sample: its dense index, or -1 for a midpoint solved by a check
  {
    // Priority 0: the ends and the knots; 1: both sides of switches and folds; 2: the grid; 3: the other steps.
    // Lower priorities join while the cap allows.
    std::vector<int> priority(n_dense, 3);
    for (int k = 0; k < n_dense; ++k) {
      const bool end = k == 0 || k == n_dense - 1 || dense_break[k] || dense[k].alpha == 0.0 || dense[k].alpha == 1.0;
      const bool rough =
          (k > 0 && dense_kind[k - 1] != kUnchecked) || (k + 1 < n_dense && dense_kind[k] != kUnchecked);
      const bool grid = std::abs(dense[k].alpha * kKeptGrid - std::round(dense[k].alpha * kKeptGrid)) < 1e-9;
      priority[k] = end ? 0 : rough ? 1 : grid ? 2 : 3;
    }
    int level = 0;
    while (level < 3 && std::count_if(priority.begin(), priority.end(), [&](int p) { return p <= level + 1; }) <=
                            options.max_samples) {
      ++level;
    }
    for (int k = 0; k < n_dense; ++k) {
      if (priority[k] <= level) dense_of.push_back(k);
    }
  }
  for (int k : dense_of) {
    path->alphas.push_back(dense[k].alpha);
    path->corrections.push_back(CorrectionField(dense[k]));
    path->tangents.push_back(TangentField(dense[k]));
    path->breaks.push_back(dense_break[k]);
  }
  for (size_t i = 0; i + 1 < dense_of.size(); ++i) {
    const bool adjacent = dense_of[i + 1] == dense_of[i] + 1;
    path->certified.push_back(adjacent ? dense_kind[dense_of[i]] : kUnchecked);
  }

  const double min_width = h / 8.0;
  std::vector<double> errors(path->certified.size(), 0.0);
  std::vector<double> parent_error(path->certified.size(), 0.0);  // the error of the interval split into this one
  for (;;) {
    std::vector<int> unchecked;
    for (size_t i = 0; i + 1 < path->alphas.size(); ++i) {
      if (path->certified[i] == kUnchecked) unchecked.push_back(static_cast<int>(i));
    }
    if (unchecked.empty()) break;
    // Each interval's check: against its inner dense samples, else (the first half of them on one solver and
    // the rest on the other) a solve at its midpoint.
    std::vector<Sample> checks(unchecked.size());
    std::vector<int> split_at(unchecked.size(), -1);  // the dense sample that would split it
    std::vector<double> check_errors(unchecked.size(), 0.0);
    std::vector<size_t> to_solve;
    for (size_t c = 0; c < unchecked.size(); ++c) {
      const int i = unchecked[c];
      const int p = dense_of[i], q = dense_of[i + 1];
      if (p < 0 || q < 0 || q - p < 2) {
        to_solve.push_back(c);
        continue;
      }
      const double middle = 0.5 * (path->alphas[i] + path->alphas[i + 1]);
      double error = 0.0, nearest = std::numeric_limits<double>::infinity();
      Eigen::MatrixXd predicted;
      for (int r = p + 1; r < q; ++r) {
        EvaluatePath(*path, dense[r].alpha, &predicted);
        error = std::max(error, dense[r].converged ? Distance(predicted, dense[r].correction) / diagonal
                                                   : std::numeric_limits<double>::infinity());
        if (std::abs(dense[r].alpha - middle) < nearest) {
          nearest = std::abs(dense[r].alpha - middle);
          split_at[c] = r;
        }
      }
      check_errors[c] = error;
    }
    const auto check = [&](PathSolver& on, size_t from, size_t to) {
      for (size_t t = from; t < to; ++t) {
        const size_t c = to_solve[t];
        const int i = unchecked[c];
        const double a = path->alphas[i], b = path->alphas[i + 1];
        if (b - a <= min_width) continue;
        Eigen::MatrixXd predicted;
        EvaluatePath(*path, 0.5 * (a + b), &predicted);
        checks[c] = on.Solve(0.5 * (a + b), nullptr, &predicted, false, kCheckIterations, path);
        check_errors[c] = checks[c].converged ? Distance(predicted, checks[c].correction) / diagonal
                                              : std::numeric_limits<double>::infinity();
      }
    };
    const size_t half = to_solve.size() / 2;
    tbb::parallel_invoke([&] { check(solver, 0, half); }, [&] { check(side, half, to_solve.size()); });
    for (size_t t = 0; t < to_solve.size(); ++t) {
      const int i = unchecked[to_solve[t]];
      path->checks += path->alphas[i + 1] - path->alphas[i] > min_width ? 1 : 0;
    }
    ThrowIfCancelled();
    std::vector<int> split;
    std::vector<Sample> added;
    std::vector<int> added_dense;
    for (size_t c = 0; c < unchecked.size(); ++c) {
      const int i = unchecked[c];
      const double a = path->alphas[i], b = path->alphas[i + 1];
      const double error = check_errors[c];
      const bool looked_up = split_at[c] >= 0;
      errors[i] = error;
      if (!looked_up && b - a <= min_width) {
        path->certified[i] = 0;
      } else if (error <= options.tolerance) {
        path->certified[i] = 1;
      } else if (path->samples() + static_cast<int>(added.size()) >= options.max_samples ||
                 (!looked_up && (!std::isfinite(error) || 0.5 * (b - a) <= min_width ||
                                 (parent_error[i] > 0.0 && error > 0.25 * parent_error[i])))) {
        // The path has all the samples it may have; or Newton did not finish from the interpolant within a
        // few iterations, or halving the interval did not bring the error down as a smooth path's would (by
        // 8 to 16): the equilibria there are not one smooth branch (a fold, a kink, nearby minima), and more
        // samples would not certify it; or its halves would be too narrow to be checked. Frames there finish by
        // a full solve when the local one fails.
        path->certified[i] = 0;
      } else {
        split.push_back(i);
        if (looked_up) {
          added.push_back(dense[split_at[c]]);
          added_dense.push_back(split_at[c]);
        } else {
          added.push_back(std::move(checks[c]));
          added_dense.push_back(-1);
        }
      }
    }
    if (split.empty()) break;
    // The solved midpoints that become samples get their exact tangents (half on each solver).
    {
      std::vector<size_t> solved;
      for (size_t a = 0; a < added.size(); ++a) {
        if (added_dense[a] < 0 && added[a].converged) solved.push_back(a);
      }
      const auto tangents = [&](PathSolver& on, size_t from, size_t to) {
        for (size_t t = from; t < to; ++t) {
          Sample& sample = added[solved[t]];
          sample.tangent = on.TangentOf(sample.alpha, sample.correction);
          sample.two_words = on.NeedsTwoWords(sample.alpha, sample.correction);
        }
      };
      const size_t half_solved = solved.size() / 2;
      tbb::parallel_invoke([&] { tangents(solver, 0, half_solved); },
                           [&] { tangents(side, half_solved, solved.size()); });
      ThrowIfCancelled();
    }
    // Insert the new samples; the split intervals' halves and their neighbours (whose tangents changed) are
    // checked again.
    TargetPath next;
    std::vector<std::uint8_t> certified;
    std::vector<double> next_errors, next_parent;
    std::vector<int> next_dense;
    size_t s = 0;
    for (size_t i = 0; i < path->alphas.size(); ++i) {
      const bool own_ends = HasTangent(*path, static_cast<int>(i)) && HasTangent(*path, static_cast<int>(i) + 1);
      next.alphas.push_back(path->alphas[i]);
      next.corrections.push_back(std::move(path->corrections[i]));
      next.tangents.push_back(std::move(path->tangents[i]));
      next.breaks.push_back(path->breaks[i]);
      next_dense.push_back(dense_of[i]);
      if (i + 1 == path->alphas.size()) break;
      if (s < split.size() && split[s] == static_cast<int>(i)) {
        if (added_dense[s] < 0 && !added[s].converged) ++path->unconverged;
        next.alphas.push_back(added[s].alpha);
        next.corrections.push_back(CorrectionField(added[s]));
        next.tangents.push_back(TangentField(added[s]));
        next.breaks.push_back(0);
        next_dense.push_back(added_dense[s]);
        for (int half_interval = 0; half_interval < 2; ++half_interval) {
          certified.push_back(kUnchecked);
          next_errors.push_back(0.0);
          // Halving pays or not is judged for solved midpoints only (looked-up ones cost nothing).
          next_parent.push_back(added_dense[s] < 0 ? errors[i] : 0.0);
        }
        ++s;
      } else {
        // A neighbour's interpolant changed only where one of its ends has no exact tangent (its slope is then
        // taken from the samples beside it). With both, it is the cubic Hermite of its own two samples, and
        // checking it again would solve the same midpoint from the same start: on the face's jawOpen path,
        // 10 of 71 checks (1.6 s of the build's CPU), with the same samples and certificates.
        const bool neighbour = std::binary_search(split.begin(), split.end(), static_cast<int>(i) - 1) ||
                               std::binary_search(split.begin(), split.end(), static_cast<int>(i) + 1);
        const std::uint8_t kind = path->certified[i];
        certified.push_back(neighbour && !own_ends && kind != kSwitch && kind != kFold ? kUnchecked : kind);
        next_errors.push_back(errors[i]);
        next_parent.push_back(parent_error[i]);
      }
    }
    path->alphas = std::move(next.alphas);
    path->corrections = std::move(next.corrections);
    path->tangents = std::move(next.tangents);
    path->breaks = std::move(next.breaks);
    path->certified = std::move(certified);
    dense_of = std::move(next_dense);
    errors = std::move(next_errors);
    parent_error = std::move(next_parent);
  }
  // Every certified interval was last checked against the final interpolant.
  path->max_error = 0.0;
  for (size_t i = 0; i < errors.size(); ++i) {
    if (path->certified[i] == 1) path->max_error = std::max(path->max_error, errors[i]);
  }
  path->solves = solver.solves + side.solves;
  path->newton_iterations = solver.newton_iterations + side.newton_iterations;
  path->tangent_cg_iterations = solver.tangent_cg_iterations + side.tangent_cg_iterations;
  path->local_checks = solver.local_checks + side.local_checks;
  path->build_ms = Elapsed(start);
}

}  // namespace

int TargetPath::uncertified() const {
  return static_cast<int>(std::count(certified.begin(), certified.end(), std::uint8_t{0}) +
                          std::count(certified.begin(), certified.end(), kFold));
}

std::vector<std::pair<double, double>> TargetPath::UncertifiedRanges() const {
  std::vector<std::pair<double, double>> ranges;
  for (size_t i = 0; i < certified.size() && i + 1 < alphas.size(); ++i) {
    if (certified[i] != 0 && certified[i] != kFold) continue;
    if (!ranges.empty() && ranges.back().second == alphas[i]) {
      ranges.back().second = alphas[i + 1];
    } else {
      ranges.emplace_back(alphas[i], alphas[i + 1]);
    }
  }
  return ranges;
}

std::int64_t TargetPath::bytes() const {
  std::int64_t total = static_cast<std::int64_t>(alphas.size() * (sizeof(double) + 2));
  for (const PathField& c : corrections) total += c.bytes();
  for (const PathField& t : tangents) total += t.bytes();
  return total;
}

std::int64_t TargetPath::stored_bytes() const {
  std::int64_t total = 0;
  for (const PathField& c : corrections) total += c.stored_bytes();
  for (const PathField& t : tangents) total += t.stored_bytes();
  return total;
}

bool TargetChangesLengths(const Rig& rig, int target) {
  for (const auto& knot : rig.internals().controls.targets[target]) {
    if (rig.target_changes_lengths(knot.shape)) return true;
  }
  return false;
}

std::vector<TargetPath> BuildTargetPaths(const Rig& rig, const TargetPathsOptions& options, TargetPathsReport* report) {
  const auto start = std::chrono::steady_clock::now();
  const int targets = rig.num_targets();
  std::vector<TargetPath> paths(targets);
  std::mutex mutex;
  tbb::parallel_for(0, targets, [&](int t) {
    if (!TargetChangesLengths(rig, t)) return;
    // Isolated: a thread that waits inside this target's path (for its other chain) runs that path's work only,
    // never another target's. Without, it would start the next target while its own is in flight, each holding
    // its two chains' factorizations: more targets in memory at once than there are threads.
    tbb::this_task_arena::isolate([&] { BuildPath(rig, t, options, &paths[t]); });
    if (options.spool) {
      // Each field once it is final; one that cannot be written (a full disk) stays in memory, with the rest.
      try {
        for (PathField& c : paths[t].corrections) c.MoveTo(options.spool);
        for (PathField& d : paths[t].tangents) d.MoveTo(options.spool);
      } catch (const Error& e) {
        std::lock_guard lock(mutex);
        if (report->spool_error.empty()) report->spool_error = e.what();
      }
    }
    if (options.done) {
      std::lock_guard lock(mutex);
      options.done(t, paths[t]);
    }
  });
  for (const TargetPath& p : paths) {
    report->samples += p.samples();
    report->solves += p.solves;
    report->unconverged += p.unconverged;
    report->uncertified += p.uncertified();
    report->newton_iterations += p.newton_iterations;
    report->max_error = std::max(report->max_error, p.max_error);
  }
  report->ms = Elapsed(start);
  return paths;
}

}  // namespace springblend::internal
