// The bake (bake.h): the options' checks, the local frame source, the baked rig's evaluator, and the bake itself:
// each target's path and its in-betweens (bake_inbetweens.cc), then the combinations and the pairs' search.
#include "springblend/bake.h"

#include <fmt/format.h>
#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <set>

#include "bake_internals.h"
#include "rig_internals.h"
#include "springblend/error.h"

namespace springblend {

// The in-betweens' part of the bake (bake_inbetweens.cc).
using internal::ChooseInbetweens;
using internal::ChordErrors;
using internal::Distance;
using internal::Inbetweens;
using internal::LocateSnaps;
using internal::SegmentErrors;

namespace {

// A lower bound of the largest error at the samples of any piecewise-linear path with `count` interior knots,
// wherever the knots are and whatever the path's values (continuous or not). Whatever the knots, the samples fall
// into count + 1 runs of consecutive samples, each within one straight piece L. For samples i < k < j of one run,
// p_k minus the chord of p_i and p_j at k equals e_k - (1 - s) e_i - s e_j with e the piece's errors (L is its own
// chord), so the piece's largest error is at least half the chord error err[i][j]. The least, over every split of
// the samples into runs, of the largest such half is the bound (dynamic programming, as KnotSearch).
double PiecewiseLinearFloor(const SegmentErrors& err, int count) {
  const int n = static_cast<int>(err.size()) - 1;
  const double inf = std::numeric_limits<double>::infinity();
  // low[r][j]: the least bound over samples 0..j split into r + 1 runs.
  std::vector<double> low(n + 1);
  for (int j = 0; j <= n; ++j) low[j] = 0.5 * err[0][j];
  for (int r = 1; r <= count; ++r) {
    std::vector<double> next(n + 1, inf);
    for (int j = 0; j <= n; ++j) {
      next[j] = low[j];  // fewer runs than allowed
      for (int i = 1; i <= j; ++i) next[j] = std::min(next[j], std::max(low[i - 1], 0.5 * err[i][j]));
    }
    low = std::move(next);
  }
  return low[n];
}

// A lower bound of the largest error, over a pair's frames at weights {0, 1/2, 1}^2 (grid[i][j]: the solved shape
// with the first target at i/2 and the second at j/2), of any rig that plays the pair as each target alone (any
// function of its own weight: in-betweens, however many) plus a corrective on by the product of the weights. On a
// rectangle of the grid with corners (a1, b1), (a2, b2), the mixed difference F(a2, b2) - F(a1, b2) - F(a2, b1) +
// F(a1, b1) of such a rig is its corrective times the rectangle's area A, whatever its in-betweens; so the solved
// shapes' mixed differences D over A must agree between rectangles up to the rig's errors: |D_R / A_R - D_S / A_S|
// is at most 4 E / A_R + 4 E / A_S, for every vertex and every two rectangles R and S.
double PairFloor(const std::array<std::array<const Points*, 3>, 3>& grid) {
  struct Rectangle {
    Points slope;  // D / A
    double area = 0.0;
  };
  std::vector<Rectangle> rectangles;
  constexpr int kSpans[3][2] = {{0, 1}, {1, 2}, {0, 2}};
  for (const auto& sa : kSpans) {
    for (const auto& sb : kSpans) {
      const double area = 0.25 * (sa[1] - sa[0]) * (sb[1] - sb[0]);
      const Points difference =
          *grid[sa[1]][sb[1]] - *grid[sa[0]][sb[1]] - *grid[sa[1]][sb[0]] + *grid[sa[0]][sb[0]];
      rectangles.push_back({difference / area, area});
    }
  }
  double floor = 0.0;
  for (size_t r = 0; r < rectangles.size(); ++r) {
    for (size_t q = r + 1; q < rectangles.size(); ++q) {
      const double gap = std::sqrt((rectangles[r].slope - rectangles[q].slope).rowwise().squaredNorm().maxCoeff());
      floor = std::max(floor, gap / (4.0 / rectangles[r].area + 4.0 / rectangles[q].area));
    }
  }
  return floor;
}

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

}  // namespace

void BakeOptions::Validate() const {
  const auto bad = [](const std::string& what) { throw Error(ErrorCode::kInvalidInput, "bake options: " + what); };
  if (samples < 2 || samples > 1024) bad(fmt::format("samples = {} is outside [2, 1024]", samples));
  if (inbetweens < 0 || inbetweens > samples - 1) {
    bad(fmt::format("inbetweens = {} is outside [0, samples - 1 = {}]", inbetweens, samples - 1));
  }
  if (!(tolerance >= 0.0) || !std::isfinite(tolerance)) bad(fmt::format("tolerance = {} must be >= 0", tolerance));
  if (!(pair_threshold > 0.0 && pair_threshold < 1.0)) {
    bad(fmt::format("pair_threshold = {} is outside (0, 1)", pair_threshold));
  }
  if (!(region_fraction > 0.0 && region_fraction < 1.0)) {
    bad(fmt::format("region_fraction = {} is outside (0, 1)", region_fraction));
  }
  if (pair_mode == BakePairs::kList && pairs.empty()) bad("the pair list is empty");
}

FrameSource LocalFrameSource(std::shared_ptr<const Rig> rig, SolveOptions options) {
  options.Validate();
  return [rig = std::move(rig), options](const std::vector<std::vector<double>>& weights,
                                         std::vector<SolvedShape>* out) {
    for (const auto& w : weights) ValidateWeights(*rig, w);
    out->assign(weights.size(), SolvedShape{});
    tbb::enumerable_thread_specific<std::unique_ptr<Solver>> solvers;
    tbb::parallel_for(tbb::blocked_range<size_t>(0, weights.size(), 1), [&](const tbb::blocked_range<size_t>& range) {
      std::unique_ptr<Solver>& solver = solvers.local();
      if (!solver) solver = std::make_unique<Solver>(rig, options);
      for (size_t i = range.begin(); i != range.end(); ++i) {
        Frame frame;
        frame.weights = weights[i];
        const SolveSummary summary = solver->Solve(frame, &(*out)[i].positions);
        (*out)[i].converged = summary.converged();
      }
    });
  };
}

BakeInput BakeInputOf(const Rig& rig) {
  BakeInput input;
  input.rest = rig.rest().vertices;
  input.target_names = rig.target_names();
  input.diagonal = rig.summary().bounding_box_diagonal;
  const auto& combinations = rig.internals().controls.combinations;
  for (size_t c = 0; c < combinations.size(); ++c) {
    input.combinations.push_back({rig.combination_names()[c], combinations[c].drivers});
  }
  return input;
}

Points BakedRig::Evaluate(const std::vector<double>& weights) const {
  if (weights.size() != targets.size()) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("{} weights for a baked rig of {} targets", weights.size(), targets.size()));
  }
  Points out = rest;
  for (size_t t = 0; t < targets.size(); ++t) {
    const double w = weights[t];
    if (w == 0.0) continue;
    const BakedTarget& target = targets[t];
    const size_t knots = target.inbetweens.size() + 1;
    const auto weight_of = [&](size_t i) { return i < target.inbetweens.size() ? target.inbetweens[i].weight : 1.0; };
    const auto shape_of = [&](size_t i) -> const Points& {
      return i < target.inbetweens.size() ? target.inbetweens[i].positions : target.full;
    };
    size_t i = 0;
    while (i + 1 < knots && w > weight_of(i)) ++i;
    const double a = i == 0 ? 0.0 : weight_of(i - 1);
    const double b = weight_of(i);
    const double u = (w - a) / (b - a);
    out += u * (shape_of(i) - rest);
    if (i > 0) out += (1.0 - u) * (shape_of(i - 1) - rest);
  }
  for (const BakedCombination& c : combinations) {
    double product = 1.0;
    for (int d : c.drivers) product *= weights[d];
    if (product == 0.0) continue;
    out += product * (c.shape - rest);
    for (int d : c.drivers) out -= product * (targets[d].full - rest);
  }
  return out;
}

BakedRig BakeRig(const BakeInput& input, const FrameSource& frames, const BakeOptions& options) {
  options.Validate();
  const auto start = std::chrono::steady_clock::now();
  const int m = static_cast<int>(input.target_names.size());
  if (m == 0) throw Error(ErrorCode::kInvalidInput, "the rig has no targets to bake");
  if (!(input.diagonal > 0.0)) throw Error(ErrorCode::kInvalidInput, "the rest shape has no extent");
  BakedRig baked;
  baked.rest = input.rest;
  baked.diagonal = input.diagonal;
  BakeSummary& summary = baked.summary;
  summary.solved_inbetweens = options.solved_inbetweens;
  const auto solve = [&](const std::vector<std::vector<double>>& weights, std::vector<SolvedShape>* out) {
    frames(weights, out);
    if (out->size() != weights.size()) {
      throw Error(ErrorCode::kInternal, fmt::format("{} frames solved for {} asked", out->size(), weights.size()));
    }
    for (const SolvedShape& s : *out) {
      if (s.positions.rows() != input.rest.rows() || s.positions.cols() != 3 || !s.positions.allFinite()) {
        throw Error(ErrorCode::kNumerical, "a solved frame has not the rest shape's vertices or is not finite");
      }
      summary.unconverged_frames += s.converged ? 0 : 1;
    }
    summary.frames += static_cast<int>(weights.size());
  };
  const auto unit = [&](const std::vector<int>& on) {
    std::vector<double> w(m, 0.0);
    for (int t : on) w[t] = 1.0;
    return w;
  };

  // 1. Each target's path at samples + 1 weights in [0, 1] (the rest shape at 0 is the rig's own), one target at
  // a time (a production face's samples of every target at once would be hundreds of MB), its snaps located, and
  // 2. its in-betweens.
  const int uniform = options.samples;
  baked.targets.resize(m);
  std::vector<Points> halfway(m);  // each target's solved shape at 1/2, where a sample lies there (the pairs' floor)
  for (int t = 0; t < m; ++t) {
    std::vector<double> alphas(uniform + 1);
    for (int j = 0; j <= uniform; ++j) alphas[j] = static_cast<double>(j) / uniform;
    const auto alone = [&](double alpha) {
      std::vector<double> w(m, 0.0);
      w[t] = alpha;
      return w;
    };
    std::vector<std::vector<double>> weights;
    for (int j = 1; j <= uniform; ++j) weights.push_back(alone(alphas[j]));
    std::vector<SolvedShape> solved;
    solve(weights, &solved);
    std::vector<Points> shapes(uniform + 1);
    shapes[0] = input.rest;
    for (int j = 1; j <= uniform; ++j) shapes[j] = std::move(solved[j - 1].positions);
    const int snaps = LocateSnaps(
        [&](const std::vector<double>& at, std::vector<Points>* out) {
          std::vector<std::vector<double>> w;
          for (double a : at) w.push_back(alone(a));
          std::vector<SolvedShape> middles;
          solve(w, &middles);
          out->clear();
          for (SolvedShape& middle : middles) out->push_back(std::move(middle.positions));
        },
        &alphas, &shapes);
    summary.snaps += snaps;
    const int n = static_cast<int>(shapes.size()) - 1;
    const auto choosing = std::chrono::steady_clock::now();
    const SegmentErrors chords = ChordErrors(shapes, alphas, input.diagonal);
    Inbetweens chosen = ChooseInbetweens(shapes, alphas, chords, options, input.diagonal);
    const double floor = PiecewiseLinearFloor(chords, static_cast<int>(chosen.knots.size()));
    summary.inbetweens_ms += Elapsed(choosing);
    BakedTarget& target = baked.targets[t];
    target.name = input.target_names[t];
    target.snaps = snaps;
    for (size_t k = 0; k < chosen.knots.size(); ++k) {
      target.inbetweens.push_back({alphas[chosen.knots[k]], std::move(chosen.values[k])});
    }
    target.full = shapes[n];
    for (int j = 0; j <= n; ++j) {
      if (alphas[j] == 0.5) halfway[t] = shapes[j];
    }
    target.max_error = chosen.error;
    double linear = 0.0;
    for (int j = 1; j < n; ++j) {
      linear = std::max(linear, Distance(shapes[j], (1.0 - alphas[j]) * shapes[0] + alphas[j] * shapes[n]));
    }
    target.linear_error = linear / input.diagonal;
    target.floor = floor;
    if (options.progress) options.progress("paths", t + 1, m);
  }
  for (const BakedTarget& t : baked.targets) {
    summary.max_error = std::max(summary.max_error, t.max_error);
    summary.linear_max_error = std::max(summary.linear_max_error, t.linear_error);
    summary.floor = std::max(summary.floor, t.floor);
  }

  // 3. Combinations: the rig's own, and the pairs asked for or found. A pair is a candidate where the two
  // targets move a common region; it is kept where its solved mix is farther than the threshold from the baked
  // rig without it (any pair the list names is kept).
  struct Candidate {
    std::string name;
    std::vector<int> drivers;
    bool from_rig = false;
    bool forced = false;
  };
  std::vector<Candidate> candidates;
  std::set<std::vector<int>> taken;
  for (const BakeInput::Combination& c : input.combinations) {
    std::vector<int> drivers = c.drivers;
    std::sort(drivers.begin(), drivers.end());
    if (drivers.size() < 2 || drivers.back() >= m || !taken.insert(drivers).second) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("combination '{}' has no valid drivers", c.name));
    }
    candidates.push_back({c.name, drivers, true, true});
  }
  const auto index_of = [&](const std::string& name) {
    const auto it = std::find(input.target_names.begin(), input.target_names.end(), name);
    if (it == input.target_names.end()) {
      std::string known;
      for (const auto& k : input.target_names) known += (known.empty() ? "" : ", ") + k;
      throw Error(ErrorCode::kNotFound, fmt::format("pair '{}': not a target of this rig (targets: {})", name, known));
    }
    return static_cast<int>(it - input.target_names.begin());
  };
  if (options.pair_mode == BakePairs::kList) {
    for (const auto& [a, b] : options.pairs) {
      std::vector<int> drivers = {index_of(a), index_of(b)};
      if (drivers[0] == drivers[1]) {
        throw Error(ErrorCode::kInvalidInput, fmt::format("pair '{}*{}' names one target twice", a, b));
      }
      std::sort(drivers.begin(), drivers.end());
      if (!taken.insert(drivers).second) continue;
      candidates.push_back({a + "_" + b, drivers, false, true});
    }
  } else if (options.pair_mode == BakePairs::kAuto) {
    // The region each target moves: vertices moving by more than region_fraction of its largest move.
    std::vector<std::vector<char>> region(m);
    for (int t = 0; t < m; ++t) {
      const Eigen::VectorXd move = (baked.targets[t].full - input.rest).rowwise().norm();
      const double largest = move.size() > 0 ? move.maxCoeff() : 0.0;
      region[t].assign(move.size(), 0);
      for (Eigen::Index v = 0; v < move.size(); ++v) {
        region[t][v] = largest > 0.0 && move[v] > options.region_fraction * largest;
      }
    }
    for (int a = 0; a < m; ++a) {
      for (int b = a + 1; b < m; ++b) {
        bool common = false;
        for (size_t v = 0; v < region[a].size() && !common; ++v) common = region[a][v] && region[b][v];
        if (!common || taken.count({a, b})) continue;
        taken.insert({a, b});
        candidates.push_back({input.target_names[a] + "_" + input.target_names[b], {a, b}, false, false});
        ++summary.candidate_pairs;
      }
    }
  }
  // Solved with their drivers at 1; placed smallest first, so that a larger combination's sculpt accounts for
  // the smaller ones among its drivers (each is then reproduced exactly with its drivers at 1).
  std::stable_sort(candidates.begin(), candidates.end(),
                   [](const Candidate& a, const Candidate& b) { return a.drivers.size() < b.drivers.size(); });
  std::vector<std::vector<double>> weights;
  for (const Candidate& c : candidates) weights.push_back(unit(c.drivers));
  // A pair found by the search must also pay inside its range: its frames with both at 1/2 and each at 1 with the
  // other at 1/2 (a corrective is on by the product of the weights, while the solved mix need not grow that way).
  constexpr double kChecks[3][2] = {{0.5, 0.5}, {1.0, 0.5}, {0.5, 1.0}};
  std::vector<size_t> checks_of(candidates.size(), 0);
  for (size_t c = 0; c < candidates.size(); ++c) {
    if (candidates[c].forced) continue;
    checks_of[c] = weights.size();
    for (const auto& check : kChecks) {
      std::vector<double> w(m, 0.0);
      w[candidates[c].drivers[0]] = check[0];
      w[candidates[c].drivers[1]] = check[1];
      weights.push_back(std::move(w));
    }
  }
  std::vector<SolvedShape> mixes;
  if (!weights.empty()) solve(weights, &mixes);
  // The pairs' floor, where the pair's frames on the grid {0, 1/2, 1}^2 are all solved.
  for (size_t c = 0; c < candidates.size(); ++c) {
    const Candidate& candidate = candidates[c];
    const int a = candidate.drivers[0];
    if (candidate.forced || halfway[a].size() == 0 || halfway[candidate.drivers[1]].size() == 0) continue;
    const int b = candidate.drivers[1];
    const std::array<std::array<const Points*, 3>, 3> grid = {{
        {&input.rest, &halfway[b], &baked.targets[b].full},
        {&halfway[a], &mixes[checks_of[c]].positions, &mixes[checks_of[c] + 2].positions},
        {&baked.targets[a].full, &mixes[checks_of[c] + 1].positions, &mixes[c].positions},
    }};
    summary.pair_floor = std::max(summary.pair_floor, PairFloor(grid) / input.diagonal);
  }
  for (size_t c = 0; c < candidates.size(); ++c) {
    const Candidate& candidate = candidates[c];
    const std::vector<double> w = unit(candidate.drivers);
    const Points without = baked.Evaluate(w);
    const double error = Distance(mixes[c].positions, without) / input.diagonal;
    if (!candidate.forced) {
      if (error <= options.pair_threshold) continue;
      // With the corrective, a frame gains w_a w_b times what it corrects at (1, 1); kept where that lowers the
      // error summed over the four frames.
      const Points correction = mixes[c].positions - without;
      double before = error, after = 0.0;
      for (size_t k = 0; k < 3; ++k) {
        std::vector<double> at(m, 0.0);
        at[candidate.drivers[0]] = kChecks[k][0];
        at[candidate.drivers[1]] = kChecks[k][1];
        const Points base = baked.Evaluate(at);
        const Points& check = mixes[checks_of[c] + k].positions;
        before += Distance(check, base) / input.diagonal;
        after += Distance(check, base + kChecks[k][0] * kChecks[k][1] * correction) / input.diagonal;
      }
      if (!(after < before)) {
        ++summary.refused_pairs;
        continue;
      }
    }
    BakedCombination combination;
    combination.name = candidate.name;
    combination.drivers = candidate.drivers;
    combination.error_without = error;
    combination.from_rig = candidate.from_rig;
    // With its drivers at 1 the combination adds (shape - rest) less each driver's (full - rest).
    combination.shape = mixes[c].positions - without + input.rest;
    for (int d : candidate.drivers) combination.shape += baked.targets[d].full - input.rest;
    baked.combinations.push_back(std::move(combination));
    if (!candidate.from_rig) ++summary.kept_pairs;
  }
  const int considered = static_cast<int>(candidates.size());
  if (options.progress) options.progress("combinations", considered, considered);
  summary.ms = Elapsed(start);
  return baked;
}

}  // namespace springblend
