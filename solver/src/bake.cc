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

#include "rig_internals.h"
#include "springblend/error.h"

namespace springblend {

namespace {

// Largest distance of a vertex between two shapes.
double Distance(const Points& a, const Points& b) { return std::sqrt((a - b).rowwise().squaredNorm().maxCoeff()); }

// Largest error (of the diagonal) at each sample of the piecewise-linear path through the rest shape (sample 0),
// the knots' shapes at the interior samples `knots` (ascending) and the last sample.
std::vector<double> SampleErrors(const std::vector<Points>& shapes, const std::vector<double>& alphas,
                                 const std::vector<int>& knots, const std::vector<Points>& values, double diagonal) {
  const int n = static_cast<int>(shapes.size()) - 1;
  std::vector<double> errors(n + 1, 0.0);
  std::vector<int> at = {0};
  at.insert(at.end(), knots.begin(), knots.end());
  at.push_back(n);
  const auto value = [&](size_t i) -> const Points& {
    return i == 0 ? shapes[0] : i + 1 == at.size() ? shapes[n] : values[i - 1];
  };
  tbb::parallel_for(size_t{0}, at.size() - 1, [&](size_t i) {
    for (int j = at[i]; j <= at[i + 1]; ++j) {
      if (j == 0 || j == n) continue;
      const double s = (alphas[j] - alphas[at[i]]) / (alphas[at[i + 1]] - alphas[at[i]]);
      errors[j] = Distance(shapes[j], (1.0 - s) * value(i) + s * value(i + 1)) / diagonal;
    }
  });
  return errors;
}

// In-betweens chosen among the samples: the knots (interior sample indices, ascending), their shapes and the
// largest error of the piecewise-linear path through them at the samples.
struct Inbetweens {
  std::vector<int> knots;
  std::vector<Points> values;
  double error = 0.0;
  std::vector<double> vertex_errors;  // per vertex, its largest error (of the diagonal), once fitted
};

// err[i][j]: the largest error (of the diagonal) of the straight segment from sample i to sample j at the samples
// between them.
using SegmentErrors = std::vector<std::vector<double>>;
SegmentErrors ChordErrors(const std::vector<Points>& shapes, const std::vector<double>& alphas, double diagonal) {
  const int n = static_cast<int>(shapes.size()) - 1;
  SegmentErrors err(n + 1, std::vector<double>(n + 1, 0.0));
  tbb::parallel_for(0, n + 1, [&](int i) {
    for (int j = i + 2; j <= n; ++j) {
      double e = 0.0;
      for (int k = i + 1; k < j; ++k) {
        const double s = (alphas[k] - alphas[i]) / (alphas[j] - alphas[i]);
        e = std::max(e, Distance(shapes[k], (1.0 - s) * shapes[i] + s * shapes[j]));
      }
      err[i][j] = e / diagonal;
    }
  });
  return err;
}

// The knots that make the largest of their segments' costs smallest, for each count (dynamic programming over the
// samples). A segment's cost is its chord error, times `interior` when neither end is the rest shape or the full
// shape: 1 for knots on the path; about 1/2 estimates a fitted path, whose segments lie off the curve they cut,
// save where an end is held on it.
class KnotSearch {
 public:
  KnotSearch(const SegmentErrors& err, int count, double interior) : n_(static_cast<int>(err.size()) - 1) {
    const auto cost = [&](int i, int j) { return err[i][j] * (i == 0 || j == n_ ? 1.0 : interior); };
    count_ = std::min(count, n_ - 1);
    const double inf = std::numeric_limits<double>::infinity();
    // best_[k][j]: the least largest cost of a path from sample 0 to sample j through k chosen samples.
    best_.assign(count_ + 1, std::vector<double>(n_ + 1, inf));
    from_.assign(count_ + 1, std::vector<int>(n_ + 1, 0));
    for (int j = 1; j <= n_; ++j) best_[0][j] = cost(0, j);
    for (int k = 1; k <= count_; ++k) {
      for (int j = k + 1; j <= n_; ++j) {
        for (int i = k; i < j; ++i) {
          const double e = std::max(best_[k - 1][i], cost(i, j));
          if (e < best_[k][j]) {
            best_[k][j] = e;
            from_[k][j] = i;
          }
        }
      }
    }
  }
  int count() const { return count_; }
  double Error(int k) const { return best_[k][n_]; }  // with interior 1: the path's largest error at the samples
  std::vector<int> Knots(int k) const {
    std::vector<int> chosen;
    for (int j = n_, c = k; c > 0; --c) {
      j = from_[c][j];
      chosen.push_back(j);
    }
    std::reverse(chosen.begin(), chosen.end());
    return chosen;
  }

 private:
  int n_ = 0;
  int count_ = 0;
  std::vector<std::vector<double>> best_;
  std::vector<std::vector<int>> from_;
};

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

// The knots' shapes that make the largest distance of the piecewise-linear path from the samples smallest, from
// `start->values` (never worse than them): each vertex on its own (the vertices are independent, so the largest over them is then smallest too)
// by Lawson's iteratively reweighted least squares, its knots' positions the weighted least-squares fit (a
// tridiagonal system: a knot meets only its neighbours) with a slight pull towards the solved sample at the
// knot, which keeps the system regular where the weights vanish. The rest shape and the full shape are held; the
// middle of a snap (two knots at neighbouring samples) is kept midway between its sides by a weight far above the
// samples' (a frame inside the snap is then half the snap away, as with the solved shapes, not more).
// With `only`, just those vertices are fitted and start->error is the largest over them (a lower bound of the
// whole path's: a filter for trials).
void FitKnots(const std::vector<Points>& shapes, const std::vector<double>& alphas, double diagonal,
              Inbetweens* start, const std::vector<Eigen::Index>* only = nullptr) {
  const int n = static_cast<int>(shapes.size()) - 1;
  const int count = static_cast<int>(start->knots.size());
  if (count == 0 || n < 2) return;
  // Lawson's iterations converge linearly; a vertex stops after 64, or once kStalledIterations have each gained
  // less than kStall of its error.
  constexpr int kIterations = 64;
  constexpr int kStalledIterations = 8;
  constexpr double kStall = 1e-3;
  std::vector<int> at = {0};
  at.insert(at.end(), start->knots.begin(), start->knots.end());
  at.push_back(n);
  // The points the path is measured at: its segment (left knot index into `at`), its place u in it, and the
  // shape it should have there: a sample, or, midway between two knots at neighbouring samples (a snap: a frame
  // there is on one side or the other, half the snap from the segment's middle at best), midway between the two
  // sides (with the solved shapes as knots, the path is exactly there).
  struct Point {
    int segment;
    double place;
    int sample, other;
  };
  std::vector<Point> points;
  for (int i = 0; i + 1 < static_cast<int>(at.size()); ++i) {
    for (int j = std::max(at[i], 1); j < at[i + 1]; ++j) {
      points.push_back({i, (alphas[j] - alphas[at[i]]) / (alphas[at[i + 1]] - alphas[at[i]]), j, j});
    }
    if (at[i + 1] - at[i] == 1) points.push_back({i, 0.5, at[i], at[i + 1]});
  }
  const int samples = static_cast<int>(std::count_if(points.begin(), points.end(), [](const Point& q) { return q.sample == q.other; }));
  constexpr double kSnapWeight = 1e3;
  const auto target = [&](const Point& q, Eigen::Index v) -> Eigen::RowVector3d {
    return q.sample == q.other ? Eigen::RowVector3d(shapes[q.sample].row(v))
                               : Eigen::RowVector3d(0.5 * (shapes[q.sample].row(v) + shapes[q.other].row(v)));
  };
  const int m = static_cast<int>(points.size());
  const Eigen::Index fitted = only ? static_cast<Eigen::Index>(only->size()) : shapes[0].rows();
  const double ridge = 1e-6 / m;
  std::vector<double> least_of(fitted, 0.0);
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, fitted, 256), [&](const tbb::blocked_range<Eigen::Index>& r) {
    // c[k]: knot k's position (0 and count + 1 held: the rest shape and the full shape).
    std::vector<Eigen::RowVector3d> c(count + 2), best(count + 2), rhs(count + 2);
    std::vector<double> diag(count + 2), off(count + 2), weight(m), error(m);
    for (Eigen::Index f = r.begin(); f != r.end(); ++f) {
      const Eigen::Index v = only ? (*only)[f] : f;
      c[0] = shapes[0].row(v);
      c[count + 1] = shapes[n].row(v);
      for (int k = 1; k <= count; ++k) c[k] = start->values[k - 1].row(v);
      const auto errors = [&] {
        double largest = 0.0;
        for (int p = 0; p < m; ++p) {
          const Point& q = points[p];
          error[p] = ((1.0 - q.place) * c[q.segment] + q.place * c[q.segment + 1] - target(q, v)).norm();
          largest = std::max(largest, error[p]);
        }
        return largest;
      };
      double least = errors();
      best = c;
      int stalled = 0;  // iterations that lowered the vertex's largest error by less than kStall of it
      // Lawson's weights on the samples (summing to 1); a snap's middle is held midway by a fixed weight far
      // above them.
      for (int p = 0; p < m; ++p) weight[p] = points[p].sample == points[p].other ? 1.0 / samples : kSnapWeight;
      for (int iteration = 0; iteration < kIterations && least > 0.0; ++iteration) {
        // The weighted normal equations of the free knots 1..count.
        for (int k = 1; k <= count; ++k) {
          diag[k] = ridge;
          off[k] = 0.0;
          rhs[k] = ridge * shapes[at[k]].row(v);
        }
        for (int p = 0; p < m; ++p) {
          const int i = points[p].segment;
          const double a = 1.0 - points[p].place, b = points[p].place, w = weight[p];
          Eigen::RowVector3d t = target(points[p], v);
          if (i == 0) t -= a * c[0];
          if (i + 1 == count + 1) t -= b * c[count + 1];
          if (i >= 1) {
            diag[i] += w * a * a;
            rhs[i] += w * a * t;
          }
          if (i + 1 <= count) {
            diag[i + 1] += w * b * b;
            rhs[i + 1] += w * b * t;
          }
          if (i >= 1 && i + 1 <= count) off[i] += w * a * b;  // between knots i and i + 1
        }
        // Tridiagonal solve (symmetric positive definite: no pivoting).
        for (int k = 2; k <= count; ++k) {
          const double ratio = off[k - 1] / diag[k - 1];
          diag[k] -= ratio * off[k - 1];
          rhs[k] -= ratio * rhs[k - 1];
        }
        c[count] = rhs[count] / diag[count];
        for (int k = count - 1; k >= 1; --k) c[k] = (rhs[k] - off[k] * c[k + 1]) / diag[k];
        const double largest = errors();
        if (largest < least) {
          if (largest > (1.0 - kStall) * least) ++stalled;
          least = largest;
          best = c;
        } else {
          ++stalled;
        }
        if (stalled > kStalledIterations) break;
        double sum = 0.0;
        for (int p = 0; p < m; ++p) {
          if (points[p].sample == points[p].other) sum += weight[p] *= error[p];
        }
        if (!(sum > 0.0)) break;
        for (int p = 0; p < m; ++p) {
          if (points[p].sample == points[p].other) weight[p] /= sum;
        }
      }
      for (int k = 1; k <= count; ++k) start->values[k - 1].row(v) = best[k];
      least_of[f] = least / diagonal;
    }
  });
  // The largest over the vertices of their largest errors at the points.
  start->error = least_of.empty() ? 0.0 : *std::max_element(least_of.begin(), least_of.end());
  if (!only) start->vertex_errors = std::move(least_of);
}

constexpr int kKnotRounds = 8;
constexpr double kNearLargest = 0.25;

// chords: ChordErrors of the shapes.
Inbetweens ChooseInbetweens(const std::vector<Points>& shapes, const std::vector<double>& alphas,
                            const SegmentErrors& chords, const BakeOptions& options, double diagonal) {
  const int n = static_cast<int>(shapes.size()) - 1;
  const KnotSearch search(chords, options.inbetweens, 1.0);
  const auto solved = [&](int k) {
    Inbetweens in;
    in.knots = search.Knots(k);
    for (int j : in.knots) in.values.push_back(shapes[j]);
    in.error = search.Error(k);  // FitKnots's measure too: a snap's middle is exactly midway with solved shapes
    return in;
  };
  const auto met = [&](double error) { return options.tolerance > 0.0 && error <= options.tolerance; };
  if (options.solved_inbetweens) {
    for (int k = 0; k < search.count(); ++k) {
      if (met(search.Error(k))) return solved(k);
    }
    return solved(search.count());
  }
  // The knots' weights for fitted shapes: the search placed them for shapes on the path, and a fitted path's best
  // weights differ (segments with an end held on the path, at 0 and 1, want to be shorter). Each knot moves by a
  // sample while that lowers the error.
  const auto descend = [&](Inbetweens* in) {
    for (int round = 0; round < kKnotRounds; ++round) {
      bool moved = false;
      for (size_t i = 0; i < in->knots.size(); ++i) {
        // A trial is fitted first on the vertices whose error is near the largest (a lower bound of its error:
        // most trials fail there), and on all of them only where it may pay.
        std::vector<Eigen::Index> near;
        for (size_t v = 0; v < in->vertex_errors.size(); ++v) {
          if (in->vertex_errors[v] >= kNearLargest * in->error) near.push_back(static_cast<Eigen::Index>(v));
        }
        for (int step : {-1, 1}) {
          const int to = in->knots[i] + step;
          const int low = i == 0 ? 0 : in->knots[i - 1];
          const int high = i + 1 == in->knots.size() ? n : in->knots[i + 1];
          if (to <= low || to >= high) continue;
          Inbetweens trial = *in;
          trial.knots[i] = to;
          trial.values[i] = shapes[to];
          if (!near.empty()) {
            Inbetweens filter = trial;
            FitKnots(shapes, alphas, diagonal, &filter, &near);
            if (!(filter.error < in->error)) continue;
          }
          FitKnots(shapes, alphas, diagonal, &trial);
          if (trial.error < in->error) {
            *in = std::move(trial);
            moved = true;
            break;
          }
        }
      }
      if (!moved) break;
    }
  };
  const KnotSearch halved(chords, options.inbetweens, 0.5);
  Inbetweens last = solved(0);
  for (int k = 1; k <= search.count() && !met(last.error); ++k) {
    Inbetweens fitted = solved(k);
    FitKnots(shapes, alphas, diagonal, &fitted);
    {
      // The knots placed for fitted shapes.
      Inbetweens placed;
      placed.knots = halved.Knots(k);
      for (int j : placed.knots) placed.values.push_back(shapes[j]);
      placed.error = std::numeric_limits<double>::infinity();
      FitKnots(shapes, alphas, diagonal, &placed);
      if (placed.error < fitted.error) fitted = std::move(placed);
    }
    const std::vector<double> errors = SampleErrors(shapes, alphas, last.knots, last.values, diagonal);
    // The worst sample that is neither a knot nor next to one (two knots a sample apart mark a snap, which the fit
    // treats apart: the grown path would not start at the last one's error).
    int worst = -1;
    for (int j = 2; j + 1 < n; ++j) {
      const auto near = [&](int d) { return std::find(last.knots.begin(), last.knots.end(), j + d) != last.knots.end(); };
      if (!near(-1) && !near(0) && !near(1) && (worst < 0 || errors[j] > errors[worst])) worst = j;
    }
    if (worst > 0) {
      // The last in-betweens with a knot at that sample, placed on their own path (the same error).
      Inbetweens grown = last;
      const size_t at = std::upper_bound(grown.knots.begin(), grown.knots.end(), worst) - grown.knots.begin();
      const int left = at == 0 ? 0 : grown.knots[at - 1];
      const int right = at == grown.knots.size() ? n : grown.knots[at];
      const Points& a = at == 0 ? shapes[0] : grown.values[at - 1];
      const Points& b = at == grown.knots.size() ? shapes[n] : grown.values[at];
      const double s = (alphas[worst] - alphas[left]) / (alphas[right] - alphas[left]);
      Points value = (1.0 - s) * a + s * b;
      grown.knots.insert(grown.knots.begin() + static_cast<std::ptrdiff_t>(at), worst);
      grown.values.insert(grown.values.begin() + static_cast<std::ptrdiff_t>(at), std::move(value));
      FitKnots(shapes, alphas, diagonal, &grown);
      if (grown.error < fitted.error) fitted = std::move(grown);
    }
    descend(&fitted);
    last = std::move(fitted);
  }
  return last;
}

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

// Where the path snaps between two samples (a fold: the equilibrium jumps to another branch), a plain rig can
// only jump too, and does best jumping where the path does: a step between samples far longer than both steps
// beside it (kSnapStep times) is bisected, each frame solved midway joining the samples, for as long as that
// frame lies with one side (within a quarter of the gap's ends' distances), until the gap is 2^-kSnapBisections of
// a sample; a frame midway between the sides means a steep but smooth path, and ends it. Up to kMaxSnaps per
// path, the largest steps first; the gaps are bisected side by side (one batch of frames per halving). Returns
// the snaps located.
constexpr double kSnapStep = 3.0;
constexpr int kSnapBisections = 6;
constexpr int kMaxSnaps = 4;
int LocateSnaps(const std::function<void(const std::vector<double>&, std::vector<Points>*)>& solve,
                std::vector<double>* alphas, std::vector<Points>* shapes) {
  const int n = static_cast<int>(shapes->size()) - 1;
  if (n < 1) return 0;
  std::vector<double> step(n);
  for (int j = 0; j < n; ++j) step[j] = Distance((*shapes)[j], (*shapes)[j + 1]);
  std::vector<std::pair<double, int>> candidates;  // (how much longer than its neighbours, step)
  for (int j = 0; j < n; ++j) {
    const double beside = std::max(j > 0 ? step[j - 1] : 0.0, j + 1 < n ? step[j + 1] : 0.0);
    if (step[j] > 0.0 && step[j] > kSnapStep * beside) candidates.push_back({beside > 0.0 ? step[j] / beside : 1e300, j});
  }
  std::sort(candidates.begin(), candidates.end(), [](const auto& a, const auto& b) {
    return a.first != b.first ? a.first > b.first : a.second < b.second;
  });
  if (static_cast<int>(candidates.size()) > kMaxSnaps) candidates.resize(kMaxSnaps);
  struct Gap {
    double lo, hi;
    Points at_lo, at_hi;
    bool open = true;
  };
  std::vector<Gap> gaps;
  for (const auto& [ratio, j] : candidates) gaps.push_back({(*alphas)[j], (*alphas)[j + 1], (*shapes)[j], (*shapes)[j + 1]});
  const double narrowest = ((*alphas)[1] - (*alphas)[0]) / (1 << kSnapBisections);
  std::vector<std::pair<double, Points>> added;
  int located = 0;
  for (int halving = 0; halving < kSnapBisections; ++halving) {
    std::vector<double> at;
    std::vector<size_t> which;
    for (size_t g = 0; g < gaps.size(); ++g) {
      if (gaps[g].open) {
        at.push_back(0.5 * (gaps[g].lo + gaps[g].hi));
        which.push_back(g);
      }
    }
    if (at.empty()) break;
    std::vector<Points> middles;
    solve(at, &middles);
    for (size_t k = 0; k < at.size(); ++k) {
      Gap& gap = gaps[which[k]];
      const double a = Distance(middles[k], gap.at_lo), b = Distance(middles[k], gap.at_hi);
      if (a <= 0.25 * (a + b)) {
        gap.lo = at[k];
        gap.at_lo = middles[k];
      } else if (b <= 0.25 * (a + b)) {
        gap.hi = at[k];
        gap.at_hi = middles[k];
      } else {
        gap.open = false;  // midway between the sides: steep, not a snap
      }
      added.push_back({at[k], std::move(middles[k])});
      if (gap.open && gap.hi - gap.lo <= narrowest * (1.0 + 1e-9)) {
        gap.open = false;
        ++located;
      }
    }
  }
  for (auto& [alpha, shape] : added) {
    const size_t i = std::upper_bound(alphas->begin(), alphas->end(), alpha) - alphas->begin();
    alphas->insert(alphas->begin() + static_cast<std::ptrdiff_t>(i), alpha);
    shapes->insert(shapes->begin() + static_cast<std::ptrdiff_t>(i), std::move(shape));
  }
  return located;
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
