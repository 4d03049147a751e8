#include "springblend/solve.h"

#include <fmt/format.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <deque>
#include <limits>
#include <optional>

#include "hessian_pattern.h"
#include "anchor.h"
#include "rigid.h"
#include "sparse_cholesky.h"
#include "springblend/error.h"

namespace springblend {

const char* ToString(HessianMode mode) {
  switch (mode) {
    case HessianMode::kTrueWithProjectedFallback: return "true_with_projected_fallback";
    case HessianMode::kProjected: return "projected";
    case HessianMode::kAbsolute: return "absolute";
  }
  return "unknown";
}

const char* ToString(Termination termination) {
  switch (termination) {
    case Termination::kConverged: return "converged";
    case Termination::kMaxIterations: return "max_iterations";
    case Termination::kStalled: return "stalled";
    case Termination::kNumericalFailure: return "numerical_failure";
    case Termination::kLinear: return "linear";
  }
  return "unknown";
}

void SolveOptions::Validate() const {
  auto fail = [](const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); };
  if (!(residual_tolerance > 0.0 && residual_tolerance < 1.0)) {
    fail(fmt::format("solve option residual_tolerance = {} is outside (0, 1)", residual_tolerance));
  }
  if (!(step_tolerance >= 0.0 && step_tolerance < 1.0)) {
    fail(fmt::format("solve option step_tolerance = {} is outside [0, 1)", step_tolerance));
  }
  if (max_iterations < 1 || max_iterations > 10000) {
    fail(fmt::format("solve option max_iterations = {} is outside [1, 10000]", max_iterations));
  }
  if (!(max_step_fraction > 0.0 && max_step_fraction <= 1000.0)) {
    fail(fmt::format("solve option max_step_fraction = {} is outside (0, 1000]", max_step_fraction));
  }
  if (max_contact_rounds < 1 || max_contact_rounds > 1000) {
    fail(fmt::format("solve option max_contact_rounds = {} is outside [1, 1000]", max_contact_rounds));
  }
  if (!(contact_offset >= 0.0 && contact_offset <= 0.01)) {
    fail(fmt::format("solve option contact_offset = {} is outside [0, 0.01]", contact_offset));
  }
  if (max_line_search_steps < 1 || max_line_search_steps > 60) {
    fail(fmt::format("solve option max_line_search_steps = {} is outside [1, 60]",
                     max_line_search_steps));
  }
  if (max_cg_iterations < 1 || max_cg_iterations > 10000) {
    fail(fmt::format("solve option max_cg_iterations = {} is outside [1, 10000]", max_cg_iterations));
  }
  if (!(refactor_cost_ratio > 0.0 && refactor_cost_ratio <= 100.0)) {
    fail(fmt::format("solve option refactor_cost_ratio = {} is outside (0, 100]", refactor_cost_ratio));
  }
}

void ValidateWeights(const Rig& rig, const std::vector<double>& weights) {
  if (static_cast<int>(weights.size()) != rig.num_targets()) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("weights has {} entries but the rig has {} targets ({})", weights.size(),
                            rig.num_targets(), fmt::join(rig.target_names(), ", ")));
  }
  for (size_t t = 0; t < weights.size(); ++t) {
    if (!std::isfinite(weights[t])) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("weights[{}] (target '{}') is not finite ({})", t, rig.target(static_cast<int>(t)).name,
                              weights[t]));
    }
  }
}

void ValidateFrame(const Rig& rig, const Frame& frame, size_t colliders) {
  ValidateWeights(rig, frame.weights);
  const int n = rig.num_vertices();
  for (size_t i = 0; i < frame.pins.size(); ++i) {
    const Pin& pin = frame.pins[i];
    if (pin.vertex < 0 || pin.vertex >= n) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("pins[{}].vertex = {} is not a vertex (the rig has {})",
                                                        i, pin.vertex, n));
    }
    if (!pin.position.allFinite()) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("pins[{}] (vertex {}) has a non-finite position", i, pin.vertex));
    }
  }
  if (!frame.collider_transforms.empty() && frame.collider_transforms.size() != colliders) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("collider_transforms has {} entries but there are {} colliders",
                            frame.collider_transforms.size(), colliders));
  }
  for (size_t i = 0; i < frame.collider_transforms.size(); ++i) {
    const RigidTransform& m = frame.collider_transforms[i];
    if (!m.translation.allFinite() || !m.rotation.coeffs().allFinite() || m.rotation.norm() < 1e-12) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("collider_transforms[{}] is not a finite rigid transform", i));
    }
  }
}

Points LinearBlend(const Rig& rig, const std::vector<double>& weights) {
  ValidateWeights(rig, weights);
  const Points& rest = rig.rest().vertices;
  Points out = rest;
  for (int t = 0; t < rig.num_targets(); ++t) {
    if (weights[t] != 0.0) out += weights[t] * (rig.target(t).vertices - rest);
  }
  return out;
}

Points LinearBlendAll(const Rig& rig, const std::vector<double>& weights) {
  ValidateWeights(rig, weights);
  const Points& rest = rig.shape(0);
  Points out = rest;
  for (int t = 0; t < rig.num_targets(); ++t) {
    if (weights[t] != 0.0) out += weights[t] * (rig.shape(t + 1) - rest);
  }
  return out;
}

void BlendRestLengths(const Rig& rig, const std::vector<double>& weights, std::vector<double>* blended) {
  ValidateWeights(rig, weights);
  const std::vector<double>& r0 = rig.rest_lengths();
  const int m = rig.num_springs();
  blended->assign(r0.begin(), r0.end());
  double* out = blended->data();
  for (int t = 0; t < rig.num_targets(); ++t) {
    const double w = weights[t];
    if (w == 0.0 || !rig.target_changes_lengths(t)) continue;
    const double* d = rig.rest_length_delta(t).data();
    for (int q = 0; q < m; ++q) out[q] += w * d[q];
  }
  const double floor = rig.options().min_rest_length_fraction * rig.summary().mean_rest_length;
  for (int q = 0; q < m; ++q) out[q] = std::max(out[q], floor);
}

std::vector<Frame> SweepFrames(const std::vector<double>& end, int steps) {
  if (steps < 1) throw Error(ErrorCode::kInvalidInput, fmt::format("sweep needs at least 1 step, got {}", steps));
  std::vector<Frame> frames(steps);
  for (int i = 0; i < steps; ++i) {
    const double alpha = steps == 1 ? 1.0 : static_cast<double>(i) / (steps - 1);
    frames[i].weights.resize(end.size());
    for (size_t t = 0; t < end.size(); ++t) frames[i].weights[t] = alpha * end[t];
  }
  return frames;
}

namespace {

constexpr size_t kGrain = 2048;
constexpr double kNoHessian = -1.0;  // Assemble: forces only
constexpr double kNoProgress = 1e-15;  // a step this short (of the diagonal) changes nothing
constexpr double kMaxForcing = 0.1;
constexpr size_t kPredictorFrames = 3;  // the quadratic predictor's nodes    // inexact Newton: the loosest relative accuracy of a linear solve

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

}  // namespace

class Solver::Impl {
 public:
  Impl(std::shared_ptr<const Rig> rig, SolveOptions options)
      : rig_(std::move(rig)), options_(std::move(options)) {
    options_.Validate();
    cholesky_ = rig_->analyzed_cholesky().Clone();
    const int n = rig_->num_vertices();
    const int m = rig_->num_springs();
    values_.assign(rig_->hessian_pattern().matrix.row_indices.size(), 0.0);
    spring_hessian_.resize(static_cast<size_t>(6) * m);
    spring_force_.resize(static_cast<size_t>(3) * m);
    stiffness_.resize(m);
    force_.resize(3 * n);
    reaction_.resize(3 * n);
    step_.resize(3 * n);
    trial_.resize(3 * n);
    fixed_dof_.assign(3 * n, 0);
    spring_product_.resize(static_cast<size_t>(3) * m);
    cg_residual_.resize(3 * n);
    cg_preconditioned_.resize(3 * n);
    cg_direction_.resize(3 * n);
    cg_product_.resize(3 * n);
  }

  SolveSummary Solve(const Frame& frame, Points* positions);
  void Reset() { past_.clear(); }
  void SetWarmStart(const Points& all_vertices) {
    if (all_vertices.rows() != rig_->num_vertices()) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("a warm start needs {} vertices, got {}", rig_->num_vertices(), all_vertices.rows()));
    }
    previous_ = all_vertices;
    past_.clear();
    past_.push_front(PastFrame{all_vertices, std::nullopt, {}, false});
  }
  const Points& all_positions() const { return previous_; }
  void SetColliders(std::vector<Collider> colliders) {
    if (!colliders.empty() && rig_->boundary_mode() == BoundaryMode::kFloating) {
      throw Error(ErrorCode::kInvalidInput,
                  "colliders need a rig held by fixed vertices or an internal anchor; this rig has neither "
                  "(give it fixed vertices, or an interior so it gets an anchor)");
    }
    colliders_ = std::move(colliders);
  }

  std::shared_ptr<const Rig> rig_;
  SolveOptions options_;

 private:
  void PrepareFrame(const std::vector<double>& weights);
  // Spring forces and, unless shift is kNoHessian, the Hessian's values (plus `shift` on the free
  // diagonal) with Dirichlet rows and columns replaced by the identity. Compressed springs' negative
  // transverse stiffness is scaled by negative_scale (1: true Hessian, 0: projected). Returns the largest
  // force on a free degree of freedom.
  double Assemble(const Eigen::VectorXd& x, double negative_scale, double shift = kNoHessian);
  double Energy(const Eigen::VectorXd& x) const;

  // Factorize and solve the system of this frame: the full matrix with identity rows for held coordinates,
  // or, when many coordinates are held, the matrix reduced to the free ones.
  internal::FactorStatus Factorize();
  void SolveLinear(const Eigen::VectorXd& rhs, Eigen::VectorXd* x);
  void ChooseLinearSystem();
  std::vector<std::pair<int, Eigen::Vector3d>> HeldVertices(const Frame& frame, const Points& linear,
                                                            std::optional<internal::AnchorMotion>* motion) const;
  void PlaceStart(const Points& linear, const std::optional<internal::AnchorMotion>& motion,
                  const std::vector<double>& weights, const std::vector<std::pair<int, Eigen::Vector3d>>& held);
  // Newton's method from x_ with the held coordinates fixed_dof_; adds to the summary's counters.
  void Newton(SolveSummary& summary);
  // The Newton direction step_ from force_ at x_: a fresh factorization and a direct solve, or conjugate
  // gradients preconditioned by the kept factorization. False (with the summary's message) on failure.
  bool NewtonDirection(double forcing, SolveSummary& summary);
  bool FactorizeAndSolve(SolveSummary& summary);
  // Conjugate gradients on H step = force with the kept factorization as preconditioner; H is applied
  // matrix-free from the per-spring blocks of the last Assemble. False when it hit negative curvature or
  // did not reach the forcing tolerance in max_cg_iterations.
  bool PreconditionedCg(double forcing, SolveSummary& summary);
  void HessianProduct(const Eigen::VectorXd& v, Eigen::VectorXd* product);
  void ApplyPreconditioner(const Eigen::VectorXd& r, Eigen::VectorXd* z);
  bool PreconditionerUsable() const;
  // One round of the contact active set; returns whether the set changed.
  bool UpdateContacts(const std::vector<RigidTransform>& motions);

  std::unique_ptr<internal::SparseCholesky> cholesky_;
  // The system reduced to the free coordinates, analysed once per set of held coordinates.
  struct Reduced {
    std::vector<char> held;  // the fixed_dof_ mask it was built for
    internal::SymmetricPattern pattern;
    std::vector<int> gather;  // reduced entry -> full value slot
    std::vector<int> dofs;    // reduced unknown -> full coordinate
    std::unique_ptr<internal::SparseCholesky> cholesky;
    std::vector<double> values;
    Eigen::VectorXd rhs, solution;
  };
  std::unique_ptr<Reduced> reduced_;
  bool use_reduced_ = false;
  std::vector<double> rest_length_;  // r̄ for this frame
  std::vector<double> stiffness_;    // k_q for this frame
  std::vector<double> values_;
  std::vector<double> spring_hessian_;  // per spring: upper triangle of H_q (6)
  std::vector<double> spring_force_;    // per spring: force on endpoint a (3)
  std::vector<char> fixed_dof_;
  double diagonal_shift_ = 0.0;
  // The factorization kept for reuse (reuse_factorization): which system holds it and its cost.
  struct KeptFactor {
    bool valid = false;
    bool reduced = false;  // in reduced_ (its `held` mask) rather than in cholesky_
    double solves_per_factorization = 1.0;  // its cost in solves
    size_t attempt = 0;    // the rung of the factorization ladder that succeeded
    bool refactor_next = false;  // the last conjugate gradients cost too much: refactor at the next step
  } kept_;
  std::vector<double> spring_product_;  // per spring: H_q (v_a - v_b)
  Eigen::VectorXd cg_residual_, cg_preconditioned_, cg_direction_, cg_product_;
  // A direction of negative curvature of the true Hessian that the last conjugate gradients met.
  Eigen::VectorXd negative_direction_;
  bool has_negative_direction_ = false;
  bool absolute_projection_ = false;

  Eigen::VectorXd x_, force_, step_, trial_;
  std::vector<Collider> colliders_;
  struct Contact {
    int vertex;
    Eigen::Vector3d normal;  // outward normal of the obstacle where the vertex is held
  };
  std::vector<Contact> contacts_;
  std::vector<char> base_fixed_dof_;  // held coordinates of this frame before contacts
  Eigen::VectorXd reaction_;          // spring force on every coordinate, held ones included

  Points previous_;  // the last solution (all_positions)
  // The warm start and the frames before it, newest first: solutions, the anchor's motion in each frame and
  // their weights (empty for a SetWarmStart), for the predictor. Consecutive frames only, at most three.
  struct PastFrame {
    Points positions;
    std::optional<internal::AnchorMotion> motion;
    std::vector<double> weights;
    bool node;  // a converged frame: the predictor may extrapolate through it
  };
  std::deque<PastFrame> past_;
};

void Solver::Impl::PrepareFrame(const std::vector<double>& weights) {
  const Rig& rig = *rig_;
  BlendRestLengths(rig, weights, &rest_length_);
  const double floor = rig.options().min_stiffness_length * rig.summary().mean_rest_length;
  const std::array<double, kSpringKindCount> kind_stiffness = {
      rig.options().structure_stiffness, rig.options().bending_stiffness, rig.options().internal_stiffness};
  const auto& kinds = rig.spring_kind();
  for (int q = 0; q < rig.num_springs(); ++q) {
    stiffness_[q] = kind_stiffness[static_cast<int>(kinds[q])] / std::max(rest_length_[q], floor);
  }
}

double Solver::Impl::Assemble(const Eigen::VectorXd& x, double negative_scale, double shift) {
  const bool hessian = shift >= 0.0;
  const Rig& rig = *rig_;
  const int m = rig.num_springs();
  const int n = rig.num_vertices();
  const int* a = rig.spring_a().data();
  const int* b = rig.spring_b().data();
  const double tiny = 1e-12 * rig.summary().mean_rest_length;
  const auto& pattern = rig.hessian_pattern();
  const char* fixed = fixed_dof_.data();
  double* values = values_.data();

  tbb::parallel_for(tbb::blocked_range<int>(0, m, kGrain), [&](const tbb::blocked_range<int>& range) {
    for (int q = range.begin(); q != range.end(); ++q) {
      const Eigen::Vector3d d = x.segment<3>(3 * a[q]) - x.segment<3>(3 * b[q]);
      const double l = d.norm();
      const double k = stiffness_[q];
      double* hq = &spring_hessian_[6 * static_cast<size_t>(q)];
      double* fq = &spring_force_[3 * static_cast<size_t>(q)];
      Eigen::Matrix3d h;
      if (l <= tiny) {
        // Coincident endpoints: no direction to push along; a plain spring-like stiffness keeps H SPD.
        fq[0] = fq[1] = fq[2] = 0.0;
        h = k * Eigen::Matrix3d::Identity();
      } else {
        const Eigen::Vector3d u = d / l;
        const double stretch = l - rest_length_[q];
        fq[0] = -k * stretch * u[0];
        fq[1] = -k * stretch * u[1];
        fq[2] = -k * stretch * u[2];
        // H_q = k [u u^T + s (I - u u^T)], s = 1 - r̄/l; projected Newton clamps s at zero.
        double s = 1.0 - rest_length_[q] / l;
        if (s < 0.0) s = absolute_projection_ ? -s : s * negative_scale;
        h = k * ((1.0 - s) * (u * u.transpose()) + s * Eigen::Matrix3d::Identity());
      }
      hq[0] = h(0, 0), hq[1] = h(0, 1), hq[2] = h(0, 2), hq[3] = h(1, 1), hq[4] = h(1, 2), hq[5] = h(2, 2);
      if (hessian) {
        const auto& slots = pattern.spring_slots[q];
        for (int ci = 0; ci < 3; ++ci) {
          for (int cj = 0; cj < 3; ++cj) {
            const bool pinned = fixed[3 * a[q] + ci] || fixed[3 * b[q] + cj];
            values[slots[ci * 3 + cj]] = pinned ? 0.0 : -h(ci, cj);
          }
        }
      }
    }
  });

  const int* offsets = rig.vertex_spring_offsets().data();
  const int* incident = rig.vertex_springs().data();
  shift += diagonal_shift_;
  return tbb::parallel_deterministic_reduce(
      tbb::blocked_range<int>(0, n, kGrain), 0.0,
      [&](const tbb::blocked_range<int>& range, double residual) {
        for (int v = range.begin(); v != range.end(); ++v) {
          double h[6] = {0, 0, 0, 0, 0, 0};
          double f[3] = {0, 0, 0};
          for (int e = offsets[v]; e < offsets[v + 1]; ++e) {
            const int q = incident[e];
            const double sign = a[q] == v ? 1.0 : -1.0;
            const double* hq = &spring_hessian_[6 * static_cast<size_t>(q)];
            const double* fq = &spring_force_[3 * static_cast<size_t>(q)];
            for (int i = 0; i < 6; ++i) h[i] += hq[i];
            for (int i = 0; i < 3; ++i) f[i] += sign * fq[i];
          }
          for (int c = 0; c < 3; ++c) {
            const bool pinned = fixed[3 * v + c];
            reaction_[3 * v + c] = f[c];
            force_[3 * v + c] = pinned ? 0.0 : f[c];
            residual = std::max(residual, std::abs(force_[3 * v + c]));
          }
          if (hessian) {
            const auto& slots = pattern.vertex_slots[v];
            static constexpr int kRow[6] = {0, 0, 0, 1, 1, 2};
            static constexpr int kCol[6] = {0, 1, 2, 1, 2, 2};
            for (int i = 0; i < 6; ++i) {
              const bool pin_row = fixed[3 * v + kRow[i]];
              const bool pin_col = fixed[3 * v + kCol[i]];
              double value;
              if (kRow[i] == kCol[i]) {
                value = pin_row ? 1.0 : h[i] + shift;
              } else {
                value = (pin_row || pin_col) ? 0.0 : h[i];
              }
              values[slots[i]] = value;
            }
          }
        }
        return residual;
      },
      [](double l, double r) { return std::max(l, r); });
}

void Solver::Impl::ChooseLinearSystem() {
  // Holding a few coordinates (the anchor, a gauge) costs nothing in the full system; holding many (a
  // placement solve pins the whole surface, contacts and pins pile up) makes a smaller system worthwhile.
  const size_t held = static_cast<size_t>(std::count(fixed_dof_.begin(), fixed_dof_.end(), 1));
  use_reduced_ = held * 10 > fixed_dof_.size();
  if (!use_reduced_ || (reduced_ && reduced_->held == fixed_dof_)) return;
  const internal::SymmetricPattern& full = rig_->hessian_pattern().matrix;
  auto reduced = std::make_unique<Reduced>();
  reduced->held = fixed_dof_;
  std::vector<int> index(full.n, -1);
  for (int d = 0; d < full.n; ++d) {
    if (!fixed_dof_[d]) {
      index[d] = static_cast<int>(reduced->dofs.size());
      reduced->dofs.push_back(d);
    }
  }
  internal::SymmetricPattern& p = reduced->pattern;
  p.n = static_cast<int>(reduced->dofs.size());
  p.column_starts.reserve(p.n + 1);
  for (int j : reduced->dofs) {
    p.column_starts.push_back(static_cast<int>(p.row_indices.size()));
    for (int k = full.column_starts[j]; k < full.column_starts[j + 1]; ++k) {
      const int i = full.row_indices[k];
      if (index[i] < 0) continue;
      p.row_indices.push_back(index[i]);  // index is increasing, so rows stay sorted
      reduced->gather.push_back(k);
    }
  }
  p.column_starts.push_back(static_cast<int>(p.row_indices.size()));
  reduced->cholesky = internal::SparseCholesky::Create(rig_->options().linear_solver);
  reduced->cholesky->Analyze(reduced->pattern);
  reduced->values.resize(reduced->gather.size());
  reduced->rhs.resize(p.n);
  reduced->solution.resize(p.n);
  reduced_ = std::move(reduced);
}

internal::FactorStatus Solver::Impl::Factorize() {
  if (!use_reduced_) return cholesky_->Factorize(values_.data());
  Reduced& r = *reduced_;
  for (size_t e = 0; e < r.gather.size(); ++e) r.values[e] = values_[r.gather[e]];
  return r.cholesky->Factorize(r.values.data());
}

void Solver::Impl::SolveLinear(const Eigen::VectorXd& rhs, Eigen::VectorXd* x) {
  if (!use_reduced_) {
    cholesky_->Solve(rhs.data(), x->data());
    return;
  }
  Reduced& r = *reduced_;
  for (size_t i = 0; i < r.dofs.size(); ++i) r.rhs[static_cast<Eigen::Index>(i)] = rhs[r.dofs[i]];
  r.cholesky->Solve(r.rhs.data(), r.solution.data());
  x->setZero();
  for (size_t i = 0; i < r.dofs.size(); ++i) (*x)[r.dofs[i]] = r.solution[static_cast<Eigen::Index>(i)];
}

bool Solver::Impl::UpdateContacts(const std::vector<RigidTransform>& motions) {
  const Rig& rig = *rig_;
  const double offset = options_.contact_offset * rig.summary().bounding_box_diagonal;
  bool changed = false;
  // Release: a held vertex the springs pull out of the obstacle no longer needs it.
  Assemble(x_, 1.0);
  std::vector<Contact> kept;
  for (const Contact& c : contacts_) {
    if (reaction_.segment<3>(3 * c.vertex).dot(c.normal) > 10.0 * options_.residual_tolerance) {
      for (int k = 0; k < 3; ++k) fixed_dof_[3 * c.vertex + k] = base_fixed_dof_[3 * c.vertex + k];
      changed = true;
    } else {
      kept.push_back(c);
    }
  }
  contacts_ = std::move(kept);
  // Catch: mesh vertices inside an obstacle move to its surface along the penetration normal and are held.
  // Interior and cap vertices never become contacts (paper section 4).
  for (int v = 0; v < rig.num_surface_vertices(); ++v) {
    if (fixed_dof_[3 * v] && fixed_dof_[3 * v + 1] && fixed_dof_[3 * v + 2]) continue;
    for (size_t i = 0; i < colliders_.size(); ++i) {
      Eigen::Vector3d surface, normal;
      if (!colliders_[i].Penetrates(x_.segment<3>(3 * v), motions[i], &surface, &normal)) continue;
      x_.segment<3>(3 * v) = surface + offset * normal;
      fixed_dof_[3 * v] = fixed_dof_[3 * v + 1] = fixed_dof_[3 * v + 2] = 1;
      contacts_.push_back({v, normal});
      changed = true;
      break;
    }
  }
  return changed;
}

double Solver::Impl::Energy(const Eigen::VectorXd& x) const {
  const Rig& rig = *rig_;
  const int* a = rig.spring_a().data();
  const int* b = rig.spring_b().data();
  return tbb::parallel_deterministic_reduce(
      tbb::blocked_range<int>(0, rig.num_springs(), kGrain), 0.0,
      [&](const tbb::blocked_range<int>& range, double sum) {
        for (int q = range.begin(); q != range.end(); ++q) {
          const double l = (x.segment<3>(3 * a[q]) - x.segment<3>(3 * b[q])).norm();
          const double stretch = l - rest_length_[q];
          sum += 0.5 * stiffness_[q] * stretch * stretch;
        }
        return sum;
      },
      [](double l, double r) { return l + r; });
}

namespace {

// Whether points span a plane (three or more, not all on one line), so holding them removes every rigid
// motion.
bool SpansRigidly(const std::vector<Eigen::Vector3d>& points, double scale) {
  if (points.size() < 3) return false;
  const Eigen::Vector3d& p0 = points[0];
  size_t far = 0;
  for (size_t i = 1; i < points.size(); ++i) {
    if ((points[i] - p0).squaredNorm() > (points[far] - p0).squaredNorm()) far = i;
  }
  const Eigen::Vector3d axis = points[far] - p0;
  if (axis.norm() <= 1e-9 * scale) return false;
  for (const auto& p : points) {
    if ((p - p0).cross(axis).norm() > 1e-6 * scale * axis.norm()) return true;
  }
  return false;
}

}  // namespace

bool Solver::Impl::FactorizeAndSolve(SolveSummary& summary) {
  // The true Hessian converges quadratically but is indefinite where springs are compressed; when its
  // Cholesky fails, halve the compressed springs' negative transverse stiffness, then drop it (projected
  // Newton). The projected Hessian is still singular where the surface is flat at rest (a vertex inside a
  // flat region moves out of plane without stretching any spring to first order), so the last resort is
  // a Levenberg-Marquardt shift of the diagonal, growing until the factorization succeeds.
  const Rig& rig = *rig_;
  const auto factor_start = std::chrono::steady_clock::now();
  ChooseLinearSystem();
  struct Attempt {
    double negative_scale, shift;
  };
  const double k_mean = 1.0 / rig.summary().mean_rest_length;
  const std::array<Attempt, 7> attempts = {{{1.0, 0.0},
                                            {0.5, 0.0},
                                            {0.0, 0.0},
                                            {0.0, 1e-6 * k_mean},
                                            {0.0, 1e-4 * k_mean},
                                            {0.0, 1e-2 * k_mean},
                                            {0.0, 1.0 * k_mean}}};
  size_t first = options_.hessian == HessianMode::kTrueWithProjectedFallback ? 0 : 2;
  // A factorization kept as a preconditioner need not be the exact Hessian: start one rung below the
  // one that worked last time, so a known-indefinite true Hessian is not factored again and again.
  if (options_.reuse_factorization && kept_.attempt > first) first = std::max(first, kept_.attempt - 1);
  internal::FactorStatus status = internal::FactorStatus::kFailed;
  kept_.valid = false;
  size_t used = first;
  for (size_t i = first; i < attempts.size(); ++i) {
    const Attempt& attempt = attempts[i];
    Assemble(x_, attempt.negative_scale, attempt.shift);
    status = Factorize();
    ++summary.factorizations;
    if (attempt.negative_scale < 1.0) ++summary.projected_factorizations;
    if (attempt.shift > 0.0) ++summary.shifted_factorizations;
    used = i;
    if (status != internal::FactorStatus::kNotPositiveDefinite) break;
  }
  const double ms = Elapsed(factor_start);
  summary.factorize_ms += ms;
  if (status != internal::FactorStatus::kOk) {
    summary.message = "the Hessian could not be factorized even with a diagonal shift";
    return false;
  }
  const internal::SparseCholesky& factor = use_reduced_ ? *reduced_->cholesky : *cholesky_;
  kept_ = KeptFactor{true, use_reduced_, factor.SolvesPerFactorization(), used, false};
  // The per-spring blocks are left as the ladder assembled them: the line search reassembles at the new
  // iterate before any matrix-free product reads them.
  SolveLinear(force_, &step_);
  if (!step_.allFinite()) {
    summary.message = "the Newton step is not finite";
    return false;
  }
  return true;
}

bool Solver::Impl::PreconditionerUsable() const {
  if (!kept_.valid || kept_.refactor_next) return false;
  if (!kept_.reduced) return true;  // identity rows for held coordinates: SPD on any free set
  // A factorization of a reduced system covers only its free coordinates; every free one must be there.
  const std::vector<char>& held = reduced_->held;
  for (size_t d = 0; d < fixed_dof_.size(); ++d) {
    if (!fixed_dof_[d] && held[d]) return false;
  }
  return true;
}

void Solver::Impl::ApplyPreconditioner(const Eigen::VectorXd& r, Eigen::VectorXd* z) {
  if (kept_.reduced) {
    Reduced& red = *reduced_;
    for (size_t i = 0; i < red.dofs.size(); ++i) red.rhs[static_cast<Eigen::Index>(i)] = r[red.dofs[i]];
    red.cholesky->Solve(red.rhs.data(), red.solution.data());
    z->setZero();
    for (size_t i = 0; i < red.dofs.size(); ++i) (*z)[red.dofs[i]] = red.solution[static_cast<Eigen::Index>(i)];
  } else {
    cholesky_->Solve(r.data(), z->data());
  }
  // Restricted to the free coordinates of this system, an SPD preconditioner stays SPD.
  for (Eigen::Index d = 0; d < z->size(); ++d) {
    if (fixed_dof_[d]) (*z)[d] = 0.0;
  }
}

void Solver::Impl::HessianProduct(const Eigen::VectorXd& v, Eigen::VectorXd* product) {
  // H v on the free coordinates, from the per-spring blocks H_q: a spring adds H_q (v_a - v_b) to a and
  // subtracts it from b. Held coordinates are zero in v and in the product.
  const Rig& rig = *rig_;
  const int m = rig.num_springs();
  const int n = rig.num_vertices();
  const int* a = rig.spring_a().data();
  const int* b = rig.spring_b().data();
  tbb::parallel_for(tbb::blocked_range<int>(0, m, kGrain), [&](const tbb::blocked_range<int>& range) {
    for (int q = range.begin(); q != range.end(); ++q) {
      const double* h = &spring_hessian_[6 * static_cast<size_t>(q)];
      const double d0 = v[3 * a[q]] - v[3 * b[q]];
      const double d1 = v[3 * a[q] + 1] - v[3 * b[q] + 1];
      const double d2 = v[3 * a[q] + 2] - v[3 * b[q] + 2];
      double* out = &spring_product_[3 * static_cast<size_t>(q)];
      out[0] = h[0] * d0 + h[1] * d1 + h[2] * d2;
      out[1] = h[1] * d0 + h[3] * d1 + h[4] * d2;
      out[2] = h[2] * d0 + h[4] * d1 + h[5] * d2;
    }
  });
  const int* offsets = rig.vertex_spring_offsets().data();
  const int* incident = rig.vertex_springs().data();
  const double shift = diagonal_shift_;
  tbb::parallel_for(tbb::blocked_range<int>(0, n, kGrain), [&](const tbb::blocked_range<int>& range) {
    for (int vtx = range.begin(); vtx != range.end(); ++vtx) {
      double sum[3] = {0.0, 0.0, 0.0};
      for (int e = offsets[vtx]; e < offsets[vtx + 1]; ++e) {
        const int q = incident[e];
        const double sign = a[q] == vtx ? 1.0 : -1.0;
        const double* t = &spring_product_[3 * static_cast<size_t>(q)];
        for (int c = 0; c < 3; ++c) sum[c] += sign * t[c];
      }
      for (int c = 0; c < 3; ++c) {
        const int d = 3 * vtx + c;
        (*product)[d] = fixed_dof_[d] ? 0.0 : sum[c] + shift * v[d];
      }
    }
  });
}

bool Solver::Impl::PreconditionedCg(double forcing, SolveSummary& summary) {
  // force_ is zero on held coordinates, and so stay every vector below.
  const double target = forcing * force_.norm();
  const double floor = 0.1 * options_.residual_tolerance;  // no need to solve below the tolerance
  step_.setZero();
  cg_residual_ = force_;
  ApplyPreconditioner(cg_residual_, &cg_preconditioned_);
  cg_direction_ = cg_preconditioned_;
  double rz = cg_residual_.dot(cg_preconditioned_);
  for (int it = 0; it < options_.max_cg_iterations; ++it) {
    HessianProduct(cg_direction_, &cg_product_);
    ++summary.cg_iterations;
    const double curvature = cg_direction_.dot(cg_product_);
    if (!(curvature > 0.0) || !std::isfinite(curvature)) {  // indefinite along d
      if (options_.follow_negative_curvature && std::isfinite(curvature) && cg_direction_.allFinite()) {
        negative_direction_ = cg_direction_;
        has_negative_direction_ = true;
      }
      return false;
    }
    const double alpha = rz / curvature;
    step_ += alpha * cg_direction_;
    cg_residual_ -= alpha * cg_product_;
    if (cg_residual_.norm() <= target || cg_residual_.lpNorm<Eigen::Infinity>() <= floor) return true;
    ApplyPreconditioner(cg_residual_, &cg_preconditioned_);
    const double rz_next = cg_residual_.dot(cg_preconditioned_);
    cg_direction_ = cg_preconditioned_ + (rz_next / rz) * cg_direction_;
    rz = rz_next;
  }
  return false;
}

bool Solver::Impl::NewtonDirection(double forcing, SolveSummary& summary) {
  has_negative_direction_ = false;
  if (options_.reuse_factorization && PreconditionerUsable()) {
    const int cg_before = summary.cg_iterations;
    // The per-spring blocks of the last Assemble are the true Hessian's at x_ (kAbsolute: its absolute
    // value; kProjected: the projected blocks are assembled here).
    if (options_.hessian == HessianMode::kProjected) Assemble(x_, 0.0);
    bool ok = PreconditionedCg(forcing, summary);
    if (!ok && options_.hessian == HessianMode::kTrueWithProjectedFallback) {
      // Negative curvature (compressed springs) or slow progress: the projected Hessian is SPD.
      Assemble(x_, 0.0);
      ok = PreconditionedCg(forcing, summary);
      Assemble(x_, 1.0);
    }
    if (ok && step_.allFinite()) {
      // Conjugate gradients that cost a good part of a factorization say the kept one is stale.
      const double solves = summary.cg_iterations - cg_before;
      if (solves > options_.refactor_cost_ratio * kept_.solves_per_factorization) kept_.refactor_next = true;
      return true;
    }
  }
  return FactorizeAndSolve(summary);
}

void Solver::Impl::Newton(SolveSummary& summary) {
  const Rig& rig = *rig_;
  const int n = rig.num_vertices();
  const double diagonal = rig.summary().bounding_box_diagonal;
  absolute_projection_ = options_.hessian == HessianMode::kAbsolute;
  int tiny_steps = 0;
  double last_step = 0.0;  // length of the last Newton step (largest coordinate change)
  double residual = Assemble(x_, 1.0);
  if (summary.newton_iterations == 0) summary.initial_residual = residual;
  double energy = Energy(x_);
  double forcing = kMaxForcing;
  double previous_norm = 0.0;
  summary.termination = Termination::kMaxIterations;
  for (int iteration = 0;; ++iteration) {
    if (!std::isfinite(residual) || !std::isfinite(energy)) {
      summary.termination = Termination::kNumericalFailure;
      summary.message = "non-finite force or energy";
      break;
    }
    // Converged: the forces are in equilibrium and, if Newton moved at all, its last step was short
    // (a small force alone says little where the system is soft).
    if (residual <= options_.residual_tolerance && last_step <= options_.step_tolerance * diagonal) {
      summary.termination = Termination::kConverged;
      break;
    }
    if (iteration >= options_.max_iterations) {
      summary.termination = Termination::kMaxIterations;
      summary.message = fmt::format("no convergence in {} Newton iterations", options_.max_iterations);
      break;
    }
    ++summary.newton_iterations;

    // Inexact Newton (Eisenstat-Walker choice 2): solve the linear system only as accurately as the
    // progress of the outer iteration warrants, loosely far from the solution, tightly close to it.
    const double norm = force_.norm();
    if (previous_norm > 0.0) {
      const double ratio = norm / previous_norm;
      const double candidate = 0.9 * ratio * ratio;
      const double safeguard = 0.9 * forcing * forcing;
      forcing = std::min(kMaxForcing, safeguard > 0.1 ? std::max(candidate, safeguard) : candidate);
    }
    previous_norm = norm;
    if (!NewtonDirection(forcing, summary)) {
      summary.termination = Termination::kNumericalFailure;
      break;
    }

    // A step that carries a vertex further than a fraction of a spring length can pass it through its
    // neighbours and land in another (inverted) equilibrium; shorten such steps before the line search.
    double longest = 0.0;
    for (int v = 0; v < n; ++v) longest = std::max(longest, step_.segment<3>(3 * v).squaredNorm());
    longest = std::sqrt(longest);
    const double max_move = options_.max_step_fraction * rig.summary().mean_rest_length;
    if (longest > max_move) step_ *= max_move / longest;
    if (has_negative_direction_) {
      // On a saddle (a buckling lip, a compressed fold) the projected Newton step barely moves along the
      // unstable mode, and Newton crawls off it over dozens of iterations. The energy falls fastest along the
      // negative curvature the conjugate gradients met: add it, downhill and as long as a step may be, and
      // let the line search below shorten the sum (cat: 35 -> 15 Newton iterations per step).
      double d_longest = 0.0;
      for (int v = 0; v < n; ++v) {
        d_longest = std::max(d_longest, negative_direction_.segment<3>(3 * v).squaredNorm());
      }
      d_longest = std::sqrt(d_longest);
      if (d_longest > 0.0) {
        const double sign = force_.dot(negative_direction_) >= 0.0 ? 1.0 : -1.0;
        step_ += (sign * max_move / d_longest) * negative_direction_;
        longest = 0.0;
        for (int v = 0; v < n; ++v) longest = std::max(longest, step_.segment<3>(3 * v).squaredNorm());
        longest = std::sqrt(longest);
        if (longest > max_move) step_ *= max_move / longest;
      }
    }

    // Backtracking line search on the energy (Armijo). Near convergence the energy change drops below
    // its round-off; there a step is judged by the force it leaves instead.
    const double slope = -force_.dot(step_);  // dE/dt at t = 0; negative for a descent direction
    const double energy_noise = 1e-13 * std::max(energy, 1e-300);
    double t = 1.0;
    double trial_energy = 0.0;
    double trial_residual = -1.0;
    bool accepted = false;
    for (int k = 0; k < options_.max_line_search_steps && !accepted; ++k) {
      trial_residual = -1.0;
      trial_ = x_ + t * step_;
      trial_energy = Energy(trial_);
      if (trial_energy <= energy + 1e-4 * t * slope) {
        accepted = true;
      } else if (trial_energy - energy <= energy_noise) {
        trial_residual = Assemble(trial_, 1.0);
        accepted = trial_residual < residual;
      }
      if (!accepted) {
        t *= 0.5;
        ++summary.line_search_halvings;
      }
    }
    if (!accepted) {
      Assemble(x_, 1.0);  // restore the forces of the current iterate
      if (residual <= options_.residual_tolerance) {
        // In equilibrium to the tolerance; only the step check could not be completed.
        summary.termination = Termination::kConverged;
        break;
      }
      summary.termination = Termination::kStalled;
      summary.message = fmt::format("the line search found no lower energy (residual {:.3g})", residual);
      break;
    }
    x_.swap(trial_);
    energy = trial_energy;
    residual = trial_residual >= 0.0 ? trial_residual : Assemble(x_, 1.0);

    last_step = t * step_.lpNorm<Eigen::Infinity>();
    summary.last_step = last_step / diagonal;
    tiny_steps = last_step <= kNoProgress * diagonal ? tiny_steps + 1 : 0;
    if (tiny_steps >= 3 && residual > options_.residual_tolerance) {
      summary.termination = Termination::kStalled;
      summary.message = fmt::format("no progress: three steps below {:.0e} of the diagonal with residual {:.3g}",
                                    kNoProgress, residual);
      break;
    }
  }
  summary.residual = residual;
  summary.energy = energy;
}

std::vector<std::pair<int, Eigen::Vector3d>> Solver::Impl::HeldVertices(
    const Frame& frame, const Points& linear, std::optional<internal::AnchorMotion>* motion) const {
  // Boundary conditions of this frame: fixed vertices follow the linear blend, the anchor its blended
  // rigid motion, pins their positions.
  const Rig& rig = *rig_;
  std::vector<std::pair<int, Eigen::Vector3d>> held;
  for (int v : rig.fixed_vertices()) held.emplace_back(v, linear.row(v).transpose());
  if (rig.boundary_mode() == BoundaryMode::kAnchored) {
    *motion = internal::BlendAnchorMotions(rig.anchor_motions(), frame.weights);
    for (int v : rig.anchor_vertices()) {
      held.emplace_back(v, (*motion)->Apply(rig.shape(0).row(v).transpose(), rig.anchor_centroid()));
    }
  }
  for (const Pin& pin : frame.pins) held.emplace_back(pin.vertex, pin.position);
  return held;
}

void Solver::Impl::PlaceStart(const Points& linear, const std::optional<internal::AnchorMotion>& motion,
                              const std::vector<double>& weights,
                              const std::vector<std::pair<int, Eigen::Vector3d>>& held) {
  // The previous frame's equilibrium (warm start; carried along with the anchor's motion since then) or
  // the linear blendshape. When the weights keep moving along one line, as over the two or three previous
  // frames (a sweep, a slider being dragged), the start is extrapolated along the solutions' own motion by
  // the polynomial through them (a secant, then a quadratic predictor): Newton then starts O(h^2), or
  // O(h^3), rather than O(h) away from the equilibrium.
  const Rig& rig = *rig_;
  const int n = rig.num_vertices();
  x_.resize(3 * n);
  if (!options_.warm_start || past_.empty()) {
    for (int v = 0; v < n; ++v) x_.segment<3>(3 * v) = linear.row(v).transpose();
    return;
  }
  const Eigen::Vector3d& c = rig.anchor_centroid();
  // Coordinates in the frame of an anchor motion (identity without an anchor), and back.
  const auto to_local = [&](const Eigen::Vector3d& p, const std::optional<internal::AnchorMotion>& m) {
    return m ? Eigen::Vector3d(m->rotation.inverse() * (p - c - m->offset)) : p;
  };
  const auto to_world = [&](const Eigen::Vector3d& l) {
    return motion ? Eigen::Vector3d(motion->rotation * l + c + motion->offset) : l;
  };
  const bool anchored = motion.has_value() && past_[0].motion.has_value();

  // Nodes of the predictor: the positions t_k of the past frames' weights on the line from the previous
  // weights (t = 0) to this frame's (t = 1). A past frame joins while its weights lie on that line (within
  // about 8 degrees) and further back than the one before it.
  std::vector<double> nodes = {0.0};
  const std::vector<double>& w0 = past_[0].weights;
  if (options_.extrapolate && past_[0].node && w0.size() == weights.size()) {
    double d_sq = 0.0;
    for (size_t t = 0; t < weights.size(); ++t) d_sq += (weights[t] - w0[t]) * (weights[t] - w0[t]);
    for (size_t k = 1; k < past_.size() && d_sq > 0.0; ++k) {
      const std::vector<double>& wk = past_[k].weights;
      if (!past_[k].node || wk.size() != weights.size() || past_[k].motion.has_value() != anchored) break;
      double along = 0.0, off_sq = 0.0;
      for (size_t t = 0; t < weights.size(); ++t) along += (wk[t] - w0[t]) * (weights[t] - w0[t]);
      const double tk = along / d_sq;
      for (size_t t = 0; t < weights.size(); ++t) {
        const double off = wk[t] - w0[t] - tk * (weights[t] - w0[t]);
        off_sq += off * off;
      }
      // The spacing to the node before: this frame's step is at most twice the last frame's; further back,
      // steps vary by at most a factor of 2.
      const double spacing = nodes.back() - tk;  // > 0: further back
      const double last_spacing = k == 1 ? 1.0 : nodes[k - 2] - nodes[k - 1];
      const bool spaced = k == 1 ? 2.0 * spacing >= 1.0 : spacing <= 2.0 * last_spacing && 2.0 * spacing >= last_spacing;
      if (!(spacing > 0.0) || !spaced || off_sq > 0.02 * tk * tk * d_sq) break;
      nodes.push_back(tk);
    }
  }
  // The polynomial through the first `order` + 1 nodes, at t = 1, with this frame's held vertices.
  const std::optional<internal::AnchorMotion> none;
  const auto predict = [&](size_t order, Eigen::VectorXd* x) {
    std::vector<double> lagrange(order + 1, 1.0);
    for (size_t i = 0; i <= order; ++i) {
      for (size_t j = 0; j <= order; ++j) {
        if (j != i) lagrange[i] *= (1.0 - nodes[j]) / (nodes[i] - nodes[j]);
      }
    }
    for (int v = 0; v < n; ++v) {
      Eigen::Vector3d local = Eigen::Vector3d::Zero();
      for (size_t k = 0; k <= order; ++k) {
        local += lagrange[k] * to_local(past_[k].positions.row(v).transpose(), anchored ? past_[k].motion : none);
      }
      x->segment<3>(3 * v) = anchored ? to_world(local) : local;
    }
    for (const auto& [v, p] : held) x->segment<3>(3 * v) = p;
  };
  // Where the path bends sharply (a lip buckles, a contact starts) a higher order can overshoot: of the
  // predictors of every order, Newton starts from the one with the least spring energy.
  predict(nodes.size() - 1, &x_);
  if (nodes.size() == 1) return;
  double best = Energy(x_);
  for (size_t order = nodes.size() - 1; order-- > 0;) {
    predict(order, &trial_);
    const double energy = Energy(trial_);
    if (energy < best) {
      best = energy;
      x_.swap(trial_);
    }
  }
}

SolveSummary Solver::Impl::Solve(const Frame& frame, Points* positions) {
  const auto start = std::chrono::steady_clock::now();
  const Rig& rig = *rig_;
  SolveSummary summary;
  const int n = rig.num_vertices();
  const double diagonal = rig.summary().bounding_box_diagonal;
  const Points linear = LinearBlendAll(rig, frame.weights);  // validates the weights
  ValidateFrame(rig, frame, colliders_.size());
  summary.pins = static_cast<int>(frame.pins.size());
  if (options_.linear) {
    *positions = linear.topRows(rig.num_surface_vertices());
    summary.termination = Termination::kLinear;
    summary.message = "linear blendshape";
    summary.solve_ms = Elapsed(start);
    return summary;
  }
  PrepareFrame(frame.weights);

  std::optional<internal::AnchorMotion> motion;
  const auto held = HeldVertices(frame, linear, &motion);
  std::vector<Eigen::Vector3d> held_points;
  for (const auto& h : held) held_points.push_back(h.second);
  BoundaryMode mode = rig.boundary_mode();
  if (mode != BoundaryMode::kAnchored && mode != BoundaryMode::kFixedVertices) {
    mode = SpansRigidly(held_points, diagonal) ? BoundaryMode::kFixedVertices
           : held.empty()                      ? BoundaryMode::kFloating
                                               : BoundaryMode::kPartiallyFixed;
  }
  PlaceStart(linear, motion, frame.weights, held);
  std::fill(fixed_dof_.begin(), fixed_dof_.end(), 0);
  for (const auto& [v, p] : held) {
    x_.segment<3>(3 * v) = p;
    fixed_dof_[3 * v] = fixed_dof_[3 * v + 1] = fixed_dof_[3 * v + 2] = 1;
  }
  summary.fixed_vertices = static_cast<int>(std::count(fixed_dof_.begin(), fixed_dof_.end(), 1) / 3);
  diagonal_shift_ = 0.0;
  if (mode == BoundaryMode::kFloating) {
    // 3-2-1 gauge: move the start rigidly so gauge vertex 0 is at the origin, 1 on the x axis and 2 in
    // the xy plane, then hold exactly those six coordinates. Any configuration can be moved so, hence the
    // gauge removes the rigid motions without adding a force.
    const auto& g = rig.gauge_vertices();
    if (!internal::ToCanonicalFrame(g, &x_)) {
      summary.termination = Termination::kNumericalFailure;
      summary.message = "the gauge vertices became collinear in the start configuration";
      summary.solve_ms = Elapsed(start);
      return summary;
    }
    fixed_dof_[3 * g[0]] = fixed_dof_[3 * g[0] + 1] = fixed_dof_[3 * g[0] + 2] = 1;
    fixed_dof_[3 * g[1] + 1] = fixed_dof_[3 * g[1] + 2] = 1;
    fixed_dof_[3 * g[2] + 2] = 1;
  } else if (mode == BoundaryMode::kPartiallyFixed) {
    diagonal_shift_ = 1e-8 / rig.summary().mean_rest_length;
  }

  base_fixed_dof_ = fixed_dof_;
  contacts_.clear();
  Newton(summary);
  if (!colliders_.empty() && summary.termination != Termination::kNumericalFailure) {
    // Paper section 4: hold the vertices that went inside an obstacle on its surface and solve again, and
    // let go of held ones the springs pull away from it, until nothing changes.
    std::vector<RigidTransform> motions(colliders_.size());
    if (!frame.collider_transforms.empty()) motions = frame.collider_transforms;
    while (UpdateContacts(motions)) {
      if (summary.contact_rounds == options_.max_contact_rounds) {
        summary.termination = Termination::kMaxIterations;
        summary.message = fmt::format("contacts still changing after {} rounds", options_.max_contact_rounds);
        break;
      }
      ++summary.contact_rounds;
      Newton(summary);
      if (summary.termination == Termination::kNumericalFailure) break;
    }
    summary.contacts = static_cast<int>(contacts_.size());
  }

  summary.inverted_tetrahedra = internal::CountInvertedTetrahedra(rig.tetrahedra(), x_);
  Points solved(n, 3);
  for (int v = 0; v < n; ++v) solved.row(v) = x_.segment<3>(3 * v).transpose();
  if (mode == BoundaryMode::kFloating) {
    internal::AlignRigidly(linear.topRows(rig.num_surface_vertices()), &solved);
  }
  if (summary.termination != Termination::kNumericalFailure) {
    // A frame that did not converge is a warm start, but no node for the predictor.
    past_.push_front(PastFrame{solved, motion, frame.weights, summary.converged()});
    if (past_.size() > kPredictorFrames) past_.pop_back();
    previous_ = solved;
  } else {
    past_.clear();  // never warm-start from a broken state
  }
  *positions = solved.topRows(rig.num_surface_vertices());
  if (summary.termination == Termination::kConverged) summary.message = "converged";
  summary.solve_ms = Elapsed(start);
  return summary;
}

Solver::Solver(std::shared_ptr<const Rig> rig, SolveOptions options)
    : impl_(std::make_unique<Impl>(std::move(rig), std::move(options))) {}
Solver::~Solver() = default;
Solver::Solver(Solver&&) noexcept = default;
Solver& Solver::operator=(Solver&&) noexcept = default;

SolveSummary Solver::Solve(const Frame& frame, Points* positions) {
  return impl_->Solve(frame, positions);
}
void Solver::Reset() { impl_->Reset(); }
void Solver::SetWarmStart(const Points& all_vertices) { impl_->SetWarmStart(all_vertices); }
void Solver::SetColliders(std::vector<Collider> colliders) { impl_->SetColliders(std::move(colliders)); }
const Points& Solver::all_positions() const { return impl_->all_positions(); }
const Rig& Solver::rig() const { return *impl_->rig_; }
const SolveOptions& Solver::options() const { return impl_->options_; }
void Solver::set_options(const SolveOptions& options) {
  options.Validate();
  impl_->options_ = options;
}

}  // namespace springblend
