// A target's path baked into in-betweens (bake_internals.h): its snaps located between the samples, the
// in-betweens' weights chosen among the samples and their shapes fitted to the whole path.
#include "bake_internals.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <limits>

namespace springblend::internal {

namespace {

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

}  // namespace

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

namespace {

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

}  // namespace

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

}  // namespace springblend::internal
