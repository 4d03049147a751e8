#include "target_paths.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <fmt/format.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_arena.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <deque>
#include <mutex>

#include "conjugate_gradients.h"
#include "frame_conditions.h"
#include "local_finish.h"
#include "minimizer.h"
#include "rig_internals.h"
#include "rigid.h"
#include "springblend/error.h"

namespace springblend::internal {

namespace {

constexpr int kMaxHalvings = 3;
// Newton iterations a midpoint check may take: from an interpolant within the tolerance of its equilibrium,
// Newton converges in one to three; a check that needs more is not within it, whatever it would converge to.
// On the face's jawOpen path (bench/paths_bench.cc): checks 199 Newton and 1393 CG iterations against 321 and
// 2081 with 6, the build 55 s against 62 s, 35 uncertified intervals against 50, 7 of 17 frames finished
// locally against 5.
constexpr int kCheckIterations = 3;
// A midpoint check first takes one Newton step in the span of the path's samples and tangents around it (as a
// path frame does) and is then finished where it is out of balance only (local_finish.h), at the samples'
// tolerances; where that gives up (more than kCheckSeedShare of the vertices still out of balance after the
// step, or a region beyond kCheckLocalShare of them), the capped full Newton goes on from there.
constexpr double kCheckSeedShare = 0.05;
constexpr double kCheckLocalShare = 0.15;
// A sample solved this far (of the diagonal) from its predicted start jumped to another branch.
constexpr double kJump = 1e-3;
constexpr std::uint8_t kUnchecked = 255;
constexpr std::uint8_t kSwitch = 2;
constexpr std::uint8_t kFold = 3;
// Solved steps at multiples of 1 / kKeptGrid are always kept.
constexpr double kKeptGrid = 8.0;
constexpr char kPathsMagic[8] = {'S', 'B', 'P', 'A', 'T', 'H', '0', '4'};
constexpr char kPathsMagicV3[8] = {'S', 'B', 'P', 'A', 'T', 'H', '0', '3'};  // floats; still read
constexpr char kPathsMagicV2[8] = {'S', 'B', 'P', 'A', 'T', 'H', '0', '2'};  // no tangents; still read
// Exact tangents: the central difference step in alpha of the forces and of the correction's map (their
// truncation error is of order step^2), the conjugate gradients' relative residual, and their cap (a sample
// whose tangent does not converge within it gets none).
constexpr double kTangentStep = 1e-4;
constexpr double kTangentAccuracy = 1e-6;
constexpr int kTangentCgIterations = 30;
// A single-target frame's span step uses the path's samples up to this many either side of its interval (and
// their tangents). Measured with the step taken before every frame's local finish, on the face's jawOpen
// path (bench/paths_bench.cc): 1: 13 of 17 frames finished locally, 0.9 % of the vertices solved; 2: 15 of
// 17, 0.2 %; 3: 15 of 17, 0.0 %, with half again the vectors.
constexpr int kSpanReach = 2;
constexpr int kSpanHalvings = 6;

// Work run by TBB inside a group that another task's exception cancelled (another target's path that was
// stopped) is skipped without an exception of its own: what it should have filled is empty, so stop too.
[[noreturn]] void ThrowCancelled() { throw Error(ErrorCode::kCancelled, "the rig build was cancelled"); }

void ThrowIfCancelled() {
  if (tbb::is_current_task_group_canceling()) ThrowCancelled();
}

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

// Coefficients c_j of the derivative at t of the parabola through (nodes_j, y_j): y'(t) = sum_j c_j y_j.
std::array<double, 3> ParabolaSlope(const std::array<double, 3>& nodes, double t) {
  std::array<double, 3> c{};
  for (int j = 0; j < 3; ++j) {
    double denominator = 1.0, numerator = 0.0;
    for (int k = 0; k < 3; ++k) {
      if (k == j) continue;
      denominator *= nodes[j] - nodes[k];
      double product = 1.0;
      for (int l = 0; l < 3; ++l) {
        if (l != j && l != k) product *= t - nodes[l];
      }
      numerator += product;
    }
    c[j] = numerator / denominator;
  }
  return c;
}

// The samples and weights whose sum is the interpolant at alpha (at most four samples).
struct Stencil {
  int count = 0;
  std::array<int, 4> sample{};
  std::array<double, 4> weight{};
  void Add(int k, double w) {
    for (int i = 0; i < count; ++i) {
      if (sample[i] == k) {
        weight[i] += w;
        return;
      }
    }
    sample[count] = k;
    weight[count] = w;
    ++count;
  }
  // Exact tangents (TargetPath::tangents) and their weights: at most the interval's two samples.
  int tangent_count = 0;
  std::array<int, 2> tangent_sample{};
  std::array<double, 2> tangent_weight{};
  void AddExactTangent(int k, double w) {
    tangent_sample[tangent_count] = k;
    tangent_weight[tangent_count] = w;
    ++tangent_count;
  }
};

bool HasTangent(const TargetPath& path, int k) {
  return static_cast<size_t>(k) < path.tangents.size() && !path.tangents[k].empty();
}

// An interval between two branches (a switch, a fold): no tangent carries across it.
bool Broken(std::uint8_t kind) { return kind == kSwitch || kind == kFold; }

// Whether sample k's tangent may use samples on both sides: not at a break (an in-between's weight, where the
// path has a kink), not next to the switch between branches, not at either end.
bool Smooth(const TargetPath& path, int k) {
  const int n = path.samples();
  if (k <= 0 || k >= n - 1) return false;
  if (!path.breaks.empty() && path.breaks[k] != 0) return false;
  return !Broken(path.certified[k - 1]) && !Broken(path.certified[k]);
}

// Tangent at sample k for interval i (k is i or i + 1) as sample weights.
void AddTangent(const TargetPath& path, int i, int k, double scale, Stencil* stencil) {
  if (HasTangent(path, k)) {
    stencil->AddExactTangent(k, scale);
    return;
  }
  const std::vector<double>& a = path.alphas;
  const int n = path.samples();
  std::array<int, 3> nodes{};
  if (Smooth(path, k)) {
    nodes = {k - 1, k, k + 1};
  } else {
    // One-sided, on interval i's side: the parabola through three samples of that side if they are on one
    // smooth piece, else the secant.
    const bool forward = k == i;
    const int far = forward ? k + 2 : k - 2;
    const int near = forward ? k + 1 : k - 1;
    const int middle_interval = forward ? k + 1 : k - 2;
    const bool three = far >= 0 && far < n && !Broken(path.certified[middle_interval]) &&
                       (path.breaks.empty() || path.breaks[near] == 0);
    if (!three) {
      const double h = a[near] - a[k];
      stencil->Add(near, scale / h);
      stencil->Add(k, -scale / h);
      return;
    }
    nodes = forward ? std::array<int, 3>{k, k + 1, k + 2} : std::array<int, 3>{k - 2, k - 1, k};
  }
  const auto c = ParabolaSlope({a[nodes[0]], a[nodes[1]], a[nodes[2]]}, a[k]);
  for (int j = 0; j < 3; ++j) stencil->Add(nodes[j], scale * c[j]);
}

Stencil StencilAt(const TargetPath& path, double alpha) {
  Stencil stencil;
  const std::vector<double>& a = path.alphas;
  const int n = path.samples();
  if (n == 1 || alpha <= a.front()) {
    stencil.Add(0, 1.0);
    return stencil;
  }
  if (alpha >= a.back()) {
    stencil.Add(n - 1, 1.0);
    return stencil;
  }
  const int i = static_cast<int>(std::upper_bound(a.begin(), a.end(), alpha) - a.begin()) - 1;
  const double h = a[i + 1] - a[i];
  const double s = (alpha - a[i]) / h;
  if (Broken(path.certified[i])) {
    // Between two branches (a fold or the switch somewhere inside): no tangent carries across. Each half
    // follows the branch of its own end, along that sample's exact tangent (a blend of the two branches is
    // on neither); the linear blend of the two where that end has none.
    const int near = s <= 0.5 ? i : i + 1;
    if (HasTangent(path, near)) {
      stencil.Add(near, 1.0);
      stencil.AddExactTangent(near, alpha - a[near]);
      return stencil;
    }
    stencil.Add(i, 1.0 - s);
    stencil.Add(i + 1, s);
    return stencil;
  }
  const double s2 = s * s, s3 = s2 * s;
  stencil.Add(i, 2 * s3 - 3 * s2 + 1);
  stencil.Add(i + 1, -2 * s3 + 3 * s2);
  AddTangent(path, i, i, h * (s3 - 2 * s2 + s), &stencil);
  AddTangent(path, i, i + 1, h * (s3 - s2), &stencil);
  return stencil;
}

// The samples of the path's smooth piece around alpha, up to kSpanReach on either side of its interval, and
// their exact tangents.
std::vector<const PathField*> SpanAround(const TargetPath& path, double alpha) {
  const std::vector<double>& a = path.alphas;
  const int count = path.samples();
  const int i = std::clamp(static_cast<int>(std::upper_bound(a.begin(), a.end(), alpha) - a.begin()) - 1, 0, count - 1);
  int first = i, last = std::min(i + 1, count - 1);
  if (last > first && Broken(path.certified[first])) last = first;
  while (first > 0 && first > i - kSpanReach + 1 && !Broken(path.certified[first - 1])) --first;
  while (last + 1 < count && last < i + kSpanReach && !Broken(path.certified[last])) ++last;
  std::vector<const PathField*> columns;
  for (int k = first; k <= last; ++k) {
    columns.push_back(&path.corrections[k]);
    if (HasTangent(path, k)) columns.push_back(&path.tangents[k]);
  }
  return columns;
}

// Column j of w: a correction (anchor's frame, #vertices by 3) in the frame's world, rotated by the anchor's
// motion.
void FillColumn(const PathField& field, const std::optional<AnchorMotion>& motion, SpringSystem::Columns* w, int j) {
  const Eigen::Matrix3d r = motion ? motion->rotation.toRotationMatrix() : Eigen::Matrix3d::Identity();
  const Eigen::MatrixXd c = field.Decode();
  for (Eigen::Index v = 0; v < c.rows(); ++v) w->col(j).segment<3>(3 * v) = r * c.row(v).transpose();
}

// One Newton step from x on the coefficients of w's columns (the reduced true Hessian from the blocks of the
// springs' last Evaluate at x), line-searched on the energy: x moves only to lower energy. Returns the span's
// dimension, or 0 when x did not move.
int StepInSpan(SpringSystem::Columns w, SpringSystem* springs, const std::vector<char>& held, double diagonal_shift,
               Eigen::VectorXd* x) {
  const Eigen::Index m = x->size();
  const int k = static_cast<int>(w.cols());
  if (k == 0) return 0;
  for (Eigen::Index d = 0; d < m; ++d) {
    if (held[d]) w.row(d).setZero();
  }
  // Coordinates of the span: the eigenvectors of the Gram matrix (its columns scaled to unit length), the
  // nearly dependent directions (a relative singular value below 1e-7: the samples' rounding) dropped.
  const Eigen::MatrixXd gram = w.transpose() * w;
  Eigen::VectorXd scale(k);
  for (int j = 0; j < k; ++j) scale[j] = gram(j, j) > 0.0 ? 1.0 / std::sqrt(gram(j, j)) : 0.0;
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(scale.asDiagonal() * gram * scale.asDiagonal());
  if (eigen.info() != Eigen::Success) return 0;
  const double largest = eigen.eigenvalues().maxCoeff();
  std::vector<int> kept;
  for (int j = 0; j < k; ++j) {
    if (eigen.eigenvalues()[j] > 1e-14 * largest) kept.push_back(j);
  }
  if (kept.empty()) return 0;
  Eigen::MatrixXd to(k, static_cast<Eigen::Index>(kept.size()));  // the coordinates' coefficients of the vectors
  for (size_t j = 0; j < kept.size(); ++j) {
    to.col(static_cast<Eigen::Index>(j)) =
        scale.asDiagonal() * eigen.eigenvectors().col(kept[j]) / std::sqrt(eigen.eigenvalues()[kept[j]]);
  }
  SpringSystem::Columns hw;
  springs->HessianProducts(w, held, diagonal_shift, &hw);
  const Eigen::MatrixXd reduced = to.transpose() * (w.transpose() * hw) * to;
  const Eigen::VectorXd g = to.transpose() * (w.transpose() * springs->force());
  const Eigen::LLT<Eigen::MatrixXd> llt(0.5 * (reduced + reduced.transpose()));
  if (llt.info() != Eigen::Success) return 0;
  const Eigen::VectorXd step = w * (to * llt.solve(g));
  if (!step.allFinite()) return 0;
  const double energy = springs->Energy(*x);
  Eigen::VectorXd trial(m);
  double length = 1.0;
  for (int halving = 0; halving < kSpanHalvings; ++halving, length *= 0.5) {
    trial = *x + length * step;
    if (springs->Energy(trial) < energy) {
      x->swap(trial);
      return static_cast<int>(kept.size());
    }
  }
  return 0;
}

// The span step at alpha on one target's path (RefineInPathSpan): where x is out of balance, one Newton step on
// the coefficients of the path's samples and tangents around alpha. Returns the span's dimension, or 0.
int RefineInSpanOf(const TargetPath& path, double alpha, const std::optional<AnchorMotion>& motion,
                   double residual_tolerance, SpringSystem* springs, const std::vector<char>& held,
                   double diagonal_shift, Eigen::VectorXd* x) {
  const std::vector<const PathField*> columns = SpanAround(path, alpha);
  // The forces first (the Hessian blocks only once the step is taken).
  const double start_residual = springs->Evaluate(*x, held, Curvature{}, false);
  if (!(start_residual > residual_tolerance)) return 0;
  springs->Evaluate(*x, held, Curvature{}, true);
  const int k = static_cast<int>(columns.size());
  SpringSystem::Columns w(x->size(), k);
  for (int j = 0; j < k; ++j) FillColumn(*columns[j], motion, &w, j);
  return StepInSpan(std::move(w), springs, held, diagonal_shift, x);
}

struct Sample {
  double alpha = 0.0;
  Eigen::MatrixXd correction;  // anchor's frame
  Eigen::MatrixXd tangent;     // its exact derivative in alpha, or empty
  double energy = 0.0;         // infinite when a tentative solve failed
  bool converged = false;
  bool jumped = false;         // its solve went over a fold: far from a start extrapolated along the branch
  bool fold_before = false;    // (assembled path) the interval below it is a fold
  bool two_words = false;      // stored in one word, it would start out of balance at its own alpha
};

PathField CorrectionField(const Sample& s) { return PathField(s.correction, s.two_words ? 2 : 1); }
PathField TangentField(const Sample& s) { return s.tangent.size() > 0 ? PathField(s.tangent) : PathField(); }

// The last samples of the branch a sweep follows, newest first: the polynomial through them, in the
// corrections (which vary smoothly where the linear blend carries most of the motion), predicts the next.
class Continuation {
 public:
  static constexpr size_t kOrder = 2;  // at most quadratic
  void Reset() { past_.clear(); }
  void Add(double alpha, const Points& correction, const Eigen::MatrixXd& tangent) {
    // An empty tangent stays empty (0 x 3): Points has three columns, an empty MatrixXd none.
    Points t = tangent.size() > 0 ? Points(tangent) : Points(0, 3);
    past_.push_front({alpha, correction, std::move(t)});
    if (past_.size() > kOrder + 1) past_.pop_back();
  }
  void Add(const Sample& sample) {
    if (sample.converged) Add(sample.alpha, sample.correction, sample.tangent);
  }
  // The predictions at alpha of orders 0 up to what the samples allow (none without samples). A sample
  // joins while the spacing stays within a factor 2 of the step, as the continuation's halvings keep it.
  std::vector<Points> Candidates(double alpha) const {
    std::vector<Points> out;
    size_t count = 0;
    double last = alpha;
    for (const Past& past : past_) {
      const double a = past.alpha;
      const double spacing = std::abs(last - a);
      if (count > 0 && (spacing == 0.0 || spacing > 2.5 * std::abs(alpha - past_[0].alpha))) break;
      last = a;
      ++count;
    }
    for (size_t order = 0; order < count; ++order) {
      Points p = Points::Zero(past_[0].correction.rows(), 3);
      for (size_t i = 0; i <= order; ++i) {
        double l = 1.0;
        for (size_t j = 0; j <= order; ++j) {
          if (j != i) l *= (alpha - past_[j].alpha) / (past_[i].alpha - past_[j].alpha);
        }
        p += l * past_[i].correction;
      }
      out.push_back(std::move(p));
    }
    // With exact tangents: the cubic Hermite through the last two samples (their values and tangents),
    // extrapolated, else the last sample's tangent line. Last, so that it is the one a jump is measured from.
    if (count >= 1 && past_[0].tangent.size() > 0) {
      const Past& p0 = past_[0];
      if (count >= 2 && past_[1].tangent.size() > 0) {
        const Past& p1 = past_[1];
        const double h = p0.alpha - p1.alpha, t = (alpha - p1.alpha) / h;
        const double t2 = t * t, t3 = t2 * t;
        out.push_back((2 * t3 - 3 * t2 + 1) * p1.correction + (h * (t3 - 2 * t2 + t)) * p1.tangent +
                      (-2 * t3 + 3 * t2) * p0.correction + (h * (t3 - t2)) * p0.tangent);
      } else {
        out.push_back(p0.correction + (alpha - p0.alpha) * p0.tangent);
      }
    }
    return out;
  }

 private:
  struct Past {
    double alpha;
    Points correction, tangent;
  };
  std::deque<Past> past_;
};

// Samples are solved well below the path's tolerance, so that a midpoint check measures the interpolant's
// error rather than the solves'.
MinimizerOptions SampleOptions(double tolerance) {
  MinimizerOptions options;
  options.residual_tolerance = 1e-7;
  options.step_tolerance = 0.1 * tolerance;
  // A step over a fold starts near a saddle, where following the negative curvature the conjugate gradients
  // meet leaves it sooner. On the face's jawOpen path: 933 Newton and 5390 CG iterations against 1163 and 6648,
  // the build 69 s against 78 s (bench/paths_bench.cc). Every sample still passes the full convergence test.
  options.follow_negative_curvature = true;
  return options;
}

// The solves along one target's path, sharing one spring system, linear system and minimizer (whose kept
// factorization preconditions the next sample while it stays close).
class PathSolver {
 public:
  PathSolver(const Rig& rig, int target, double tolerance, const std::function<bool()>* stop)
      : rig_(rig),
        target_(target),
        stop_(stop),
        sample_options_(SampleOptions(tolerance)),
        springs_(TopologyOf(rig)),
        linear_(rig.internals().pattern->matrix, *rig.internals().cholesky, rig.options().linear_solver),
        minimizer_(Minimizer::Create(sample_options_)),
        held_(3 * static_cast<size_t>(rig.num_vertices()), 0) {
    springs_.set_length_scale(rig.summary().mean_rest_length);
  }

  std::vector<double> Weights(double alpha) const {
    std::vector<double> weights(rig_.num_targets(), 0.0);
    weights[target_] = alpha;
    return weights;
  }

  // The target alone at alpha: its weights, linear blend and conditions, with the springs' rest lengths set.
  struct Setup {
    std::vector<double> weights;
    Points linear;
    FrameConditions conditions;
  };
  Setup SetUp(double alpha) {
    Setup setup;
    setup.weights = Weights(alpha);
    const std::vector<double> shape_weights = rig_.ShapeWeights(setup.weights);
    setup.linear = LinearBlendShapes(rig_, shape_weights);
    std::vector<double> rest_lengths;
    BlendRestLengths(rig_, shape_weights, &rest_lengths);
    springs_.SetRestLengths(std::move(rest_lengths), rig_.spring_kind(), KindStiffness(rig_.options()),
                            StiffnessFloor(rig_));
    setup.conditions = ConditionsOf(rig_, shape_weights, setup.linear, {});
    return setup;
  }

  // The sculpted shape of a knot (alpha 0, an in-between's weight, 1): a zero correction when it is in
  // balance (an unmasked shape: zero energy), else the equilibrium solved from it.
  Sample End(double alpha) {
    const Setup setup = SetUp(alpha);
    const Points& linear = setup.linear;
    Eigen::VectorXd x(3 * linear.rows());
    for (Eigen::Index v = 0; v < linear.rows(); ++v) x.segment<3>(3 * v) = linear.row(v).transpose();
    if (!HoldConditions(rig_, setup.conditions, &x, &held_) ||
        springs_.Evaluate(x, held_, Curvature{}, false) > SampleOptions(1.0).residual_tolerance) {
      const Eigen::MatrixXd zero = Eigen::MatrixXd::Zero(rig_.num_vertices(), 3);
      return Solve(alpha, nullptr, &zero);
    }
    Sample sample{alpha, Eigen::MatrixXd::Zero(rig_.num_vertices(), 3), Eigen::MatrixXd(), 0.0, true};
    sample.tangent = Tangent(alpha, std::move(x));
    return sample;
  }

  // The exact tangent at a sample given by its correction (anchor's frame).
  Eigen::MatrixXd TangentOf(double alpha, const Eigen::MatrixXd& correction) {
    const Setup setup = SetUp(alpha);
    Eigen::MatrixXd world = correction;
    if (setup.conditions.motion) world = world * setup.conditions.motion->rotation.toRotationMatrix().transpose();
    const int n = rig_.num_vertices();
    Eigen::VectorXd x(3 * n);
    for (int v = 0; v < n; ++v) x.segment<3>(3 * v) = (setup.linear.row(v) + world.row(v)).transpose();
    if (!HoldConditions(rig_, setup.conditions, &x, &held_)) return {};
    return Tangent(alpha, std::move(x));
  }

  // The exact tangent of a sample's correction, d correction / d alpha (anchor's frame), at the equilibrium x
  // of alpha (held coordinates in place, held_ marking them, the springs' rest lengths those of alpha):
  // differentiating F_f(y_f(alpha), y_h(alpha), alpha) = 0 gives H_ff y_f' = g, g the derivative of the free
  // forces in alpha with the free coordinates held (the rest lengths and the held vertices moving; central
  // differences), solved by conjugate gradients with the kept factorization as preconditioner; the
  // correction's map (minus the linear blend, rotated into the anchor's frame, or aligned for a floating
  // rig) is then differentiated along (y', 1). Empty where the sample has no smooth tangent: at or next to an
  // in-between's weight (a kink), or where the Hessian is not positive definite (a fold, a saddle).
  Eigen::MatrixXd Tangent(double alpha, Eigen::VectorXd x) {
    if (stop_ != nullptr && *stop_ && (*stop_)()) ThrowCancelled();
    const double e = kTangentStep;
    for (const auto& knot : rig_.internals().controls.targets[target_]) {
      if (knot.weight < 1.0 && std::abs(alpha - knot.weight) <= 2 * e) return {};
    }
    const int n = rig_.num_vertices();
    Eigen::VectorXd g, velocity = Eigen::VectorXd::Zero(3 * n);
    for (const double side : {1.0, -1.0}) {
      const Setup moved = SetUp(alpha + side * e);
      Eigen::VectorXd y = x;
      for (const auto& [v, p] : moved.conditions.held) y.segment<3>(3 * v) = p;
      springs_.Evaluate(y, held_, Curvature{}, false);
      if (side > 0) {
        g = springs_.force();
      } else {
        g -= springs_.force();
      }
      velocity += side * (y - x);
    }
    g /= 2 * e;
    velocity /= 2 * e;  // nonzero on the held coordinates only
    const Setup here = SetUp(alpha);
    // The kept factorization (of a nearby sample) preconditions; where there is none, or it is too far off
    // for the conjugate gradients to converge within their cap, the Hessian at x is factorized (and kept for
    // the samples after it).
    const auto factorize = [&] {
      linear_.Select(held_);
      std::vector<double> values(springs_.topology().pattern->matrix.row_indices.size());
      const LadderResult ladder = FactorizeWithLadder(
          linear_, 0, 1.0 / rig_.summary().mean_rest_length,
          [&](double negative_scale, double shift) -> const std::vector<double>& {
            springs_.Assemble(x, held_, Curvature{negative_scale, false}, shift + here.conditions.diagonal_shift,
                              &values);
            return values;
          });
      return ladder.status == FactorStatus::kOk;
    };
    bool fresh = false;
    if (!linear_.has_factor() || !linear_.FactorCovers(held_)) {
      if (!factorize()) return {};
      fresh = true;
    }
    springs_.Evaluate(x, held_, Curvature{}, true);
    ConjugateGradientsOptions options;
    options.target_norm = kTangentAccuracy * g.norm();
    options.max_iterations = kTangentCgIterations;
    if (!cg_ || cg_->last_direction().size() != g.size()) cg_ = std::make_unique<ConjugateGradients>(g.size());
    Eigen::VectorXd z(g.size());
    const auto solve = [&] {
      return cg_->Solve(
          [&](const Eigen::VectorXd& v, Eigen::VectorXd* out) {
            springs_.HessianProduct(v, held_, here.conditions.diagonal_shift, out);
          },
          [&](const Eigen::VectorXd& r, Eigen::VectorXd* out) { linear_.Precondition(r, held_, out); }, g, options, &z,
          &tangent_cg_iterations);
    };
    ConjugateGradientsStatus status = solve();
    if (status == ConjugateGradientsStatus::kMaxIterations && !fresh) {
      if (stop_ != nullptr && *stop_ && (*stop_)()) ThrowCancelled();
      if (!factorize()) return {};
      springs_.Evaluate(x, held_, Curvature{}, true);
      status = solve();
    }
    // Negative curvature: the true Hessian is not positive definite at x (a saddle, a fold): no tangent.
    if (status != ConjugateGradientsStatus::kConverged || !z.allFinite()) return {};
    velocity += z;
    // The correction's map along (y', 1).
    Points ends[2];
    for (int i = 0; i < 2; ++i) {
      const double side = i == 0 ? 1.0 : -1.0;
      const Setup at = SetUp(alpha + side * e);
      Points solved(n, 3);
      for (int v = 0; v < n; ++v) solved.row(v) = (x.segment<3>(3 * v) + side * e * velocity.segment<3>(3 * v)).transpose();
      if (at.conditions.mode == BoundaryMode::kFloating) {
        AlignRigidly(at.linear.topRows(rig_.num_surface_vertices()), &solved);
      }
      ends[i] = solved - at.linear;
      if (at.conditions.motion) ends[i] = ends[i] * at.conditions.motion->rotation.toRotationMatrix();
    }
    SetUp(alpha);
    const Points tangent = (ends[0] - ends[1]) / (2 * e);
    if (!tangent.allFinite()) return {};
    return tangent;
  }

  int solves = 0;  // equilibria solved (tentative ones that failed not counted)
  int newton_iterations = 0;
  int tangent_cg_iterations = 0;
  int local_checks = 0;  // midpoint checks finished locally

  // Solves alpha * target coming from `from` (the previous sample): where the continuation step is too long
  // for Newton to converge, it is halved (up to three times) and the path followed through the midpoints,
  // which are kept as samples too (in *out, ascending along the way).
  void Refined(double from, double alpha, Continuation& continuation, std::vector<Sample>* out, int depth = 0) {
    Continuation before = continuation;
    Sample sample = Solve(alpha, &continuation, nullptr, depth < kMaxHalvings);
    if (std::isfinite(sample.energy) || depth >= kMaxHalvings) {
      out->push_back(std::move(sample));
      return;
    }
    continuation = std::move(before);
    const double middle = 0.5 * (from + alpha);
    Refined(from, middle, continuation, out, depth + 1);
    Refined(middle, alpha, continuation, out, depth + 1);
  }

  // Solves the target at alpha from the predictor's start, or from `correction` (anchor's frame) when given.
  // A tentative solve that fails is not counted.
  // max_iterations > 0 caps the Newton iterations (a midpoint check: an interpolant Newton does not finish
  // from in a few iterations is not in its equilibrium's basin, whatever that equilibrium is).
  Sample Solve(double alpha, Continuation* continuation, const Eigen::MatrixXd* correction, bool tentative = false,
               int max_iterations = 0, const TargetPath* around = nullptr) {
    if (stop_ != nullptr && *stop_ && (*stop_)()) {
      ThrowCancelled();
    }
    const int n = rig_.num_vertices();
    const Setup setup = SetUp(alpha);
    const Points& linear = setup.linear;
    const FrameConditions& conditions = setup.conditions;
    // The start: the given correction, else the continuation's prediction with the least energy (where the
    // path bends sharply a higher order can overshoot).
    Eigen::VectorXd x;
    size_t predictions = 0;
    bool jumped = false;
    Points extrapolated, last;  // the highest-order prediction and the last sample (anchor's frame)
    const auto start_from = [&](const auto& c, Eigen::VectorXd* out) {
      Eigen::MatrixXd world = c;
      if (conditions.motion) world = world * conditions.motion->rotation.toRotationMatrix().transpose();
      out->resize(3 * n);
      for (int v = 0; v < n; ++v) out->segment<3>(3 * v) = (linear.row(v) + world.row(v)).transpose();
    };
    if (correction != nullptr) {
      start_from(*correction, &x);
    } else {
      double best = std::numeric_limits<double>::infinity();
      Eigen::VectorXd trial;
      const std::vector<Points> candidates = continuation->Candidates(alpha);
      predictions = candidates.size();
      if (predictions > 1) {
        extrapolated = candidates.back();
        last = candidates.front();
      }
      for (const Points& c : candidates) {
        start_from(c, &trial);
        HoldConditions(rig_, conditions, &trial, &held_);
        const double e = springs_.Energy(trial);
        if (!(e >= best)) {
          best = e;
          x.swap(trial);
        }
      }
      if (x.size() == 0) start_from(Eigen::MatrixXd::Zero(n, 3), &x);
    }
    MinimizerSummary summary;
    const bool held = HoldConditions(rig_, conditions, &x, &held_);
    if (held) {
      MinimizerProblem problem;
      problem.springs = &springs_;
      problem.linear = &linear_;
      problem.held = &held_;
      problem.diagonal_shift = conditions.diagonal_shift;
      problem.diagonal = rig_.summary().bounding_box_diagonal;
      problem.mean_rest_length = rig_.summary().mean_rest_length;
      problem.stop = stop_;
      MinimizerTiming timing;
      problem.timing = &timing;
      if (around == nullptr || !FinishLocally(alpha, conditions, *around, &x, &summary)) {
        if (max_iterations > 0) {
          MinimizerOptions capped = sample_options_;
          capped.max_iterations = max_iterations;
          minimizer_->SetOptions(capped);
        }
        minimizer_->Minimize(problem, &x, &summary);
        if (max_iterations > 0) minimizer_->SetOptions(sample_options_);
      }
    }
    if (summary.termination == MinimizerTermination::kCancelled) {
      ThrowCancelled();
    }
    const bool converged = summary.termination == MinimizerTermination::kConverged;
    newton_iterations += summary.iterations;
    if (!converged && tentative) {
      return {alpha, Eigen::MatrixXd(), Eigen::MatrixXd(), std::numeric_limits<double>::infinity(), false};
    }
    ++solves;
    Points solved(n, 3);
    for (int v = 0; v < n; ++v) solved.row(v) = x.segment<3>(3 * v).transpose();
    if (conditions.mode == BoundaryMode::kFloating) {
      AlignRigidly(linear.topRows(rig_.num_surface_vertices()), &solved);
    }
    const bool finite = solved.allFinite();
    if (!finite) solved = linear;  // a broken sample only costs its frames a worse start
    Points corrected = solved - linear;
    if (conditions.motion) corrected = corrected * conditions.motion->rotation.toRotationMatrix();  // R^T per row
    // A sample of the path (not a midpoint check) gets its exact tangent.
    Eigen::MatrixXd tangent;
    bool two_words = false;
    if (converged && finite && max_iterations == 0) {
      tangent = Tangent(alpha, x);
      two_words = NeedsTwoWords(alpha, corrected);
    }
    if (continuation != nullptr) {
      // A solve whose correction (aligned, for a floating rig: its gauge says nothing) landed far from the one
      // extrapolated along the branch, by more than half of what the step changed, went over a fold to
      // another branch: what came before it does not predict what comes after. (On a smooth branch the
      // extrapolation's error is of higher order in the step than the change.)
      if (predictions > 1) {
        const auto largest = [](const Points& d) { return std::sqrt(d.rowwise().squaredNorm().maxCoeff()); };
        const double missed = largest(corrected - extrapolated);
        jumped = missed > kJump * rig_.summary().bounding_box_diagonal && missed > 0.5 * largest(corrected - last);
      }
      if (jumped) continuation->Reset();
      if (converged && finite) continuation->Add(alpha, corrected, tangent);
    }
    return {alpha,
            std::move(corrected),
            std::move(tangent),
            converged && finite ? summary.energy : std::numeric_limits<double>::infinity(),
            converged && finite,
            jumped,
            false,
            two_words};
  }

  // A midpoint check's start x (the interpolant at alpha) finished as a path frame is: one Newton step in the
  // span of the path's samples and tangents around alpha, then Newton where it is still out of balance only,
  // to the samples' tolerances (the full convergence test on every free coordinate). x only moves to lower
  // energy, so where this gives up (false) the full Newton goes on from x.
  bool FinishLocally(double alpha, const FrameConditions& conditions, const TargetPath& around, Eigen::VectorXd* x,
                     MinimizerSummary* summary) {
    RefineInSpanOf(around, alpha, conditions.motion, sample_options_.residual_tolerance, &springs_, held_,
                   conditions.diagonal_shift, x);
    LocalFinishOptions finish;
    finish.residual_tolerance = sample_options_.residual_tolerance;
    finish.step_tolerance = sample_options_.step_tolerance;
    finish.max_share = kCheckLocalShare;
    finish.max_seed_share = kCheckSeedShare;
    finish.linear_solver = RegionLinearSolver(rig_.options().linear_solver);
    const LocalFinishResult result =
        LocalFinish(&springs_, held_, conditions.diagonal_shift, rig_.summary().bounding_box_diagonal,
                    rig_.summary().mean_rest_length, finish, stop_, x);
    if (stop_ != nullptr && *stop_ && (*stop_)()) ThrowCancelled();
    if (!result.converged) {
      newton_iterations += result.iterations;
      return false;
    }
    summary->iterations = result.iterations;
    ++local_checks;
    summary->termination = MinimizerTermination::kConverged;
    summary->residual = result.residual;
    summary->last_step = result.last_step;
    summary->energy = springs_.Energy(*x);
    return true;
  }

  // Whether a sample's correction (anchor's frame) needs two words (PathField): stored in one, the frame at
  // its own alpha would start out of balance, its largest free force above the samples' tolerance and half
  // again that of the correction itself.
  bool NeedsTwoWords(double alpha, const Points& correction) {
    const Setup setup = SetUp(alpha);
    const auto force_at = [&](const Eigen::MatrixXd& c) {
      Eigen::MatrixXd world = c;
      if (setup.conditions.motion) world = world * setup.conditions.motion->rotation.toRotationMatrix().transpose();
      Eigen::VectorXd x(3 * world.rows());
      for (Eigen::Index v = 0; v < world.rows(); ++v) x.segment<3>(3 * v) = (setup.linear.row(v) + world.row(v)).transpose();
      HoldConditions(rig_, setup.conditions, &x, &held_);
      return springs_.Evaluate(x, held_, Curvature{}, false);
    };
    const double own = force_at(correction);
    const double stored = force_at(PathField(correction).Decode());
    return stored > std::max(sample_options_.residual_tolerance, 1.5 * own);
  }

 private:
  const Rig& rig_;
  int target_;
  const std::function<bool()>* stop_;
  MinimizerOptions sample_options_;
  SpringSystem springs_;
  LinearSystem linear_;
  std::unique_ptr<Minimizer> minimizer_;
  std::unique_ptr<ConjugateGradients> cg_;
  std::vector<char> held_;
};

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

void EvaluatePath(const TargetPath& path, double alpha, Eigen::MatrixXd* correction) {
  const Stencil stencil = StencilAt(path, alpha);
  *correction = Eigen::MatrixXd::Zero(path.corrections[0].rows(), 3);
  for (int i = 0; i < stencil.count; ++i) {
    path.corrections[stencil.sample[i]].AddTo(stencil.weight[i], correction);
  }
  for (int i = 0; i < stencil.tangent_count; ++i) {
    path.tangents[stencil.tangent_sample[i]].AddTo(stencil.tangent_weight[i], correction);
  }
}

void AddPathCorrections(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                        const std::optional<AnchorMotion>& motion, Eigen::VectorXd* x,
                        const std::vector<double>* scale) {
  const Eigen::Index n = x->size() / 3;
  Eigen::MatrixXd sum = Eigen::MatrixXd::Zero(n, 3);
  bool any = false;
  for (size_t t = 0; t < paths.size() && t < weights.size(); ++t) {
    const TargetPath& path = paths[t];
    const double factor = scale != nullptr && t < scale->size() ? (*scale)[t] : 1.0;
    if (path.empty() || weights[t] == 0.0 || factor == 0.0) continue;
    const Stencil stencil = StencilAt(path, weights[t]);
    for (int i = 0; i < stencil.count; ++i) {
      path.corrections[stencil.sample[i]].AddTo(factor * stencil.weight[i], &sum);
    }
    for (int i = 0; i < stencil.tangent_count; ++i) {
      path.tangents[stencil.tangent_sample[i]].AddTo(factor * stencil.tangent_weight[i], &sum);
    }
    any = true;
  }
  if (!any) return;
  if (motion) sum = sum * motion->rotation.toRotationMatrix().transpose();  // R per row
  for (Eigen::Index v = 0; v < n; ++v) x->segment<3>(3 * v) += sum.row(v).transpose();
}

bool IsPathMix(const std::vector<TargetPath>& paths, const std::vector<double>& weights) {
  int corrected = 0;
  for (size_t t = 0; t < paths.size() && t < weights.size(); ++t) corrected += !paths[t].empty() && weights[t] != 0.0;
  return corrected >= 2;
}

double ScaleMixStart(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                     const Eigen::VectorXd& base, const std::function<double(const Eigen::VectorXd&)>& energy,
                     Eigen::VectorXd* x) {
  if (!IsPathMix(paths, weights) || base.size() != x->size()) return 1.0;
  constexpr int kSteps = 8;  // the ray's grid, from s = 1 down
  const Eigen::VectorXd correction = *x - base;
  std::vector<double> e(kSteps + 1, 0.0);  // e[k]: the energy at s = k / kSteps
  e[kSteps] = energy(*x);
  if (!std::isfinite(e[kSteps])) return 1.0;
  int k = kSteps;
  while (k > 0) {
    e[k - 1] = energy(base + (static_cast<double>(k - 1) / kSteps) * correction);
    if (!(e[k - 1] < e[k])) break;
    --k;
  }
  if (k == kSteps) return 1.0;
  double s = static_cast<double>(k) / kSteps, lowest = e[k];
  if (k > 0) {
    // The parabola through the grid's three energies around the lowest, at its vertex (inside, as e[k] is below
    // both neighbours).
    const double curvature = e[k - 1] - 2.0 * e[k] + e[k + 1];
    if (curvature > 0.0) {
      const double vertex = (k + 0.5 * (e[k - 1] - e[k + 1]) / curvature) / kSteps;
      const double at = energy(base + vertex * correction);
      if (at < lowest) lowest = at, s = vertex;
    }
  }
  *x = base + s * correction;
  return s;
}

namespace {

// The one target a frame moves, or -1.
int MovedTarget(const std::vector<double>& weights) {
  int moved = -1;
  for (size_t t = 0; t < weights.size(); ++t) {
    if (weights[t] == 0.0) continue;
    if (moved >= 0) return -1;  // a mix: its equilibrium is not in one path's span
    moved = static_cast<int>(t);
  }
  return moved;
}

}  // namespace

bool HasPathSpan(const std::vector<TargetPath>& paths, const std::vector<double>& weights) {
  const int moved = MovedTarget(weights);
  return moved >= 0 && static_cast<size_t>(moved) < paths.size() && !paths[moved].empty();
}

int RefineInPathSpan(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                     const std::optional<AnchorMotion>& motion, double residual_tolerance, SpringSystem* springs,
                     const std::vector<char>& held, double diagonal_shift, Eigen::VectorXd* x) {
  if (!HasPathSpan(paths, weights)) return 0;
  const int moved = MovedTarget(weights);
  return RefineInSpanOf(paths[moved], weights[moved], motion, residual_tolerance, springs, held, diagonal_shift, x);
}

namespace {

template <typename T>
void Put(std::string* out, const T& value) {
  out->append(reinterpret_cast<const char*>(&value), sizeof(T));
}

// Reads the serialized paths from memory or from a file (whose fields are then left there: PathField::Stored).
class Cursor {
 public:
  explicit Cursor(const std::string& in) : in_(&in), size_(in.size()) {}
  Cursor(std::shared_ptr<const PathFile> file, std::int64_t offset, size_t size)
      : file_(std::move(file)), offset_(offset), size_(size) {}
  template <typename T>
  bool Get(T* value) {
    return GetBytes(value, sizeof(T));
  }
  bool GetBytes(void* out, size_t n) {
    if (n > left()) return false;
    if (n > 0) {
      if (in_ != nullptr) {
        std::memcpy(out, in_->data() + at_, n);
      } else {
        file_->Read(offset_ + static_cast<std::int64_t>(at_), n, out);
      }
    }
    at_ += n;
    return true;
  }
  size_t left() const { return size_ - at_; }
  bool GetField(Eigen::Index rows, PathField* field) {
    if (in_ != nullptr) return PathField::Parse(*in_, &at_, rows, field);
    char header[PathField::kHeaderBytes];
    double step = 0.0;
    int words = 0;
    if (rows <= 0 || !GetBytes(header, sizeof(header)) || !PathField::ParseHeader(header, &step, &words)) return false;
    const size_t words_size = sizeof(std::int32_t) * 3 * static_cast<size_t>(rows);
    if (left() / words_size < static_cast<size_t>(words)) return false;
    *field = PathField::Stored(file_, offset_ + static_cast<std::int64_t>(at_), rows, words, step);
    at_ += words_size * static_cast<size_t>(words);
    return true;
  }
  // A float field of the older versions, in fixed point (held in memory).
  bool GetFloatField(Eigen::Index rows, PathField* field) {
    Eigen::MatrixXf f(rows, 3);
    if (!GetBytes(f.data(), sizeof(float) * 3 * static_cast<size_t>(rows)) || !f.allFinite()) return false;
    *field = PathField(f.cast<double>());
    return true;
  }

 private:
  const std::string* in_ = nullptr;
  std::shared_ptr<const PathFile> file_;
  std::int64_t offset_ = 0;
  size_t size_ = 0;
  size_t at_ = 0;
};

}  // namespace

bool WriteTargetPaths(const std::vector<TargetPath>& paths, const std::function<bool(std::string_view)>& write) {
  constexpr size_t kPiece = size_t{4} << 20;  // bytes gathered before they are told
  std::string out(kPathsMagic, sizeof(kPathsMagic));
  const auto flush = [&](size_t at_least) {
    if (out.size() < at_least) return true;
    const bool ok = write(out);
    out.clear();
    return ok;
  };
  const std::uint32_t vertices = [&] {
    for (const TargetPath& p : paths) {
      if (!p.empty()) return static_cast<std::uint32_t>(p.corrections[0].rows());
    }
    return std::uint32_t{0};
  }();
  Put<std::uint32_t>(&out, static_cast<std::uint32_t>(paths.size()));
  Put<std::uint32_t>(&out, vertices);
  for (const TargetPath& p : paths) {
    Put<std::uint32_t>(&out, static_cast<std::uint32_t>(p.samples()));
    if (p.empty()) continue;
    Put<double>(&out, p.max_error);
    Put<std::int32_t>(&out, p.solves);
    Put<std::int32_t>(&out, p.newton_iterations);
    Put<std::int32_t>(&out, p.unconverged);
    for (double a : p.alphas) Put<double>(&out, a);
    out.append(reinterpret_cast<const char*>(p.breaks.data()), p.breaks.size());
    out.append(reinterpret_cast<const char*>(p.certified.data()), p.certified.size());
    // Version 4: fixed point (PathField), in one or two words.
    for (const PathField& c : p.corrections) {
      c.AppendTo(&out);
      if (!flush(kPiece)) return false;
    }
    // Version 3: per sample, whether it has an exact tangent, then those tangents.
    for (int k = 0; k < p.samples(); ++k) out.push_back(HasTangent(p, k) ? 1 : 0);
    for (int k = 0; k < p.samples(); ++k) {
      if (!HasTangent(p, k)) continue;
      p.tangents[k].AppendTo(&out);
      if (!flush(kPiece)) return false;
    }
  }
  return flush(1);
}

std::string SerializeTargetPaths(const std::vector<TargetPath>& paths) {
  std::string bytes;
  WriteTargetPaths(paths, [&](std::string_view piece) {
    bytes.append(piece);
    return true;
  });
  return bytes;
}

namespace {

std::optional<std::vector<TargetPath>> ParsePaths(Cursor& in, int targets, int vertices, std::string* why) {
  char magic[sizeof(kPathsMagic)];
  if (!in.GetBytes(magic, sizeof(magic)) || (std::memcmp(magic, kPathsMagic, sizeof(magic)) != 0 &&
                                              std::memcmp(magic, kPathsMagicV3, sizeof(magic)) != 0 &&
                                              std::memcmp(magic, kPathsMagicV2, sizeof(magic)) != 0)) {
    *why = "not target paths of a known version";
    return std::nullopt;
  }
  const bool fixed_point = std::memcmp(magic, kPathsMagic, sizeof(magic)) == 0;
  const bool with_tangents = fixed_point || std::memcmp(magic, kPathsMagicV3, sizeof(magic)) == 0;
  const auto get_field = [&](Eigen::Index n, PathField* field) {
    return fixed_point ? in.GetField(n, field) : in.GetFloatField(n, field);
  };
  std::uint32_t count = 0, rows = 0;
  if (!in.Get(&count) || !in.Get(&rows)) {
    *why = "truncated";
    return std::nullopt;
  }
  if (static_cast<int>(count) != targets) {
    *why = fmt::format("{} paths for {} targets", count, targets);
    return std::nullopt;
  }
  std::vector<TargetPath> paths(count);
  for (TargetPath& p : paths) {
    std::uint32_t samples = 0;
    if (!in.Get(&samples)) {
      *why = "truncated";
      return std::nullopt;
    }
    if (samples == 0) continue;
    if (static_cast<int>(rows) != vertices) {
      *why = fmt::format("paths of {} vertices for a rig of {}", rows, vertices);
      return std::nullopt;
    }
    // At least (every version's field takes at least a float per coordinate).
    const size_t need = samples * (sizeof(double) + 2 + sizeof(float) * 3 * static_cast<size_t>(rows));
    if (samples < 2 || need > in.left()) {
      *why = "truncated";
      return std::nullopt;
    }
    bool ok = in.Get(&p.max_error) && in.Get(&p.solves) && in.Get(&p.newton_iterations) &&
              in.Get(&p.unconverged);
    p.alphas.resize(samples);
    p.breaks.resize(samples);
    p.certified.resize(samples - 1);
    ok = ok && in.GetBytes(p.alphas.data(), sizeof(double) * samples) && in.GetBytes(p.breaks.data(), samples) &&
         in.GetBytes(p.certified.data(), samples - 1);
    for (std::uint32_t k = 0; ok && k < samples; ++k) {
      PathField c;
      ok = get_field(rows, &c);
      p.corrections.push_back(std::move(c));
    }
    p.tangents.assign(samples, PathField());
    if (ok && with_tangents) {
      std::vector<std::uint8_t> has(samples);
      ok = in.GetBytes(has.data(), samples);
      for (std::uint32_t k = 0; ok && k < samples; ++k) {
        if (has[k] > 1) ok = false;
        if (!ok || has[k] == 0) continue;
        ok = get_field(rows, &p.tangents[k]);
      }
    }
    for (std::uint32_t k = 0; ok && k + 1 < samples; ++k) {
      ok = std::isfinite(p.alphas[k]) && p.alphas[k] < p.alphas[k + 1] && p.certified[k] <= kFold;
    }
    if (!ok) {
      *why = "malformed samples";
      return std::nullopt;
    }
  }
  if (in.left() != 0) {
    *why = "trailing bytes";
    return std::nullopt;
  }
  return paths;
}

}  // namespace

std::optional<std::vector<TargetPath>> ParseTargetPaths(const std::string& bytes, int targets, int vertices,
                                                        std::string* why) {
  Cursor in(bytes);
  return ParsePaths(in, targets, vertices, why);
}

std::optional<std::vector<TargetPath>> ParseTargetPaths(std::shared_ptr<const PathFile> file, std::int64_t offset,
                                                        std::int64_t size, int targets, int vertices,
                                                        std::string* why) {
  if (size < 0) size = file->size() - offset;
  if (offset < 0 || size < 0 || offset > file->size() || size > file->size() - offset) {
    *why = fmt::format("'{}' holds {} bytes, not {} at {}", file->path(), file->size(), size, offset);
    return std::nullopt;
  }
  Cursor in(std::move(file), offset, static_cast<size_t>(size));
  return ParsePaths(in, targets, vertices, why);
}

}  // namespace springblend::internal
