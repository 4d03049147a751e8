// A target path's interpolant (target_paths.h): the samples and tangents that sum to it at a weight, and what
// frames take from it: their corrections, a mix's scaled start, and the span step of a single-target frame.
#include "target_paths.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include <algorithm>
#include <array>
#include <cmath>

#include "path_internals.h"

namespace springblend::internal {

namespace {

// A single-target frame's span step uses the path's samples up to this many either side of its interval (and
// their tangents). Measured with the step taken before every frame's local finish, on the face's jawOpen
// path (bench/paths_bench.cc): 1: 13 of 17 frames finished locally, 0.9 % of the vertices solved; 2: 15 of
// 17, 0.2 %; 3: 15 of 17, 0.0 %, with half again the vectors.
constexpr int kSpanReach = 2;
constexpr int kSpanHalvings = 6;

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

}  // namespace

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

}  // namespace springblend::internal
