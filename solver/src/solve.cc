// The per-frame solve: blend the rest lengths, hold the frame's boundary conditions (fixed vertices, the
// anchor's blended motion, pins, a gauge), start from the predictor, minimize, and repeat around the
// contact active set (paper sections 3.2-3.4 and 4).
#include "springblend/solve.h"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <optional>

#include "anchor.h"
#include "boundary_conditions.h"
#include "contact_set.h"
#include "linear_system.h"
#include "minimizer.h"
#include "predictor.h"
#include "rig_internals.h"
#include "rigid.h"
#include "spring_system.h"
#include "springblend/error.h"

namespace springblend {

namespace {

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

internal::MinimizerOptions ToMinimizerOptions(const SolveOptions& o) {
  internal::MinimizerOptions m;
  m.type = internal::MinimizerType::kInexactNewton;
  m.residual_tolerance = o.residual_tolerance;
  m.step_tolerance = o.step_tolerance;
  m.max_iterations = o.max_iterations;
  m.max_line_search_steps = o.max_line_search_steps;
  m.hessian = o.hessian == HessianMode::kProjected  ? internal::HessianChoice::kProjected
              : o.hessian == HessianMode::kAbsolute ? internal::HessianChoice::kAbsolute
                                                    : internal::HessianChoice::kTrueWithProjectedFallback;
  m.reuse_factorization = o.reuse_factorization;
  m.max_cg_iterations = o.max_cg_iterations;
  m.refactor_cost_ratio = o.refactor_cost_ratio;
  m.follow_negative_curvature = o.follow_negative_curvature;
  m.max_step_fraction = o.max_step_fraction;
  return m;
}

Termination ToTermination(internal::MinimizerTermination t) {
  switch (t) {
    case internal::MinimizerTermination::kConverged: return Termination::kConverged;
    case internal::MinimizerTermination::kMaxIterations: return Termination::kMaxIterations;
    case internal::MinimizerTermination::kStalled: return Termination::kStalled;
    case internal::MinimizerTermination::kNumericalFailure: return Termination::kNumericalFailure;
  }
  return Termination::kNumericalFailure;
}

}  // namespace

class Solver::Impl {
 public:
  Impl(std::shared_ptr<const Rig> rig, SolveOptions options)
      : rig_(std::move(rig)),
        options_(std::move(options)),
        springs_(internal::TopologyOf(*rig_)),
        linear_(rig_->internals().pattern->matrix, *rig_->internals().cholesky, rig_->options().linear_solver) {
    options_.Validate();
    minimizer_ = internal::Minimizer::Create(ToMinimizerOptions(options_));
    springs_.set_length_scale(rig_->summary().mean_rest_length);
    held_.assign(3 * static_cast<size_t>(rig_->num_vertices()), 0);
  }

  SolveSummary Solve(const Frame& frame, Points* positions);
  void Reset() { predictor_.Reset(); }
  void SetWarmStart(const Points& all_vertices) {
    if (all_vertices.rows() != rig_->num_vertices()) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("a warm start needs {} vertices, got {}", rig_->num_vertices(), all_vertices.rows()));
    }
    previous_ = all_vertices;
    predictor_.SetStart(all_vertices);
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
  void SetOptions(const SolveOptions& options) {
    options.Validate();
    options_ = options;
    const internal::MinimizerOptions minimizer = ToMinimizerOptions(options_);
    if (minimizer.type == minimizer_->type()) {
      minimizer_->SetOptions(minimizer);
    } else {
      minimizer_ = internal::Minimizer::Create(minimizer);
    }
  }

  std::shared_ptr<const Rig> rig_;
  SolveOptions options_;

 private:
  // Boundary conditions of this frame: fixed vertices follow the linear blend, the anchor its blended rigid
  // motion, pins their positions.
  std::vector<std::pair<int, Eigen::Vector3d>> HeldVertices(const Frame& frame, const Points& linear,
                                                            std::optional<internal::AnchorMotion>* motion) const;
  void Minimize(double diagonal_shift, internal::MinimizerSummary* summary) {
    internal::MinimizerProblem problem;
    problem.springs = &springs_;
    problem.linear = &linear_;
    problem.held = &held_;
    problem.diagonal_shift = diagonal_shift;
    problem.diagonal = rig_->summary().bounding_box_diagonal;
    problem.mean_rest_length = rig_->summary().mean_rest_length;
    minimizer_->Minimize(problem, &x_, summary);
  }

  internal::SpringSystem springs_;
  internal::LinearSystem linear_;
  std::unique_ptr<internal::Minimizer> minimizer_;
  internal::Predictor predictor_;
  internal::ContactSet contacts_;
  std::vector<Collider> colliders_;
  std::vector<char> held_, base_held_;  // held coordinates of this frame, and before contacts
  Eigen::VectorXd x_;
  Points previous_;  // the last solution (all_positions)
};

std::vector<std::pair<int, Eigen::Vector3d>> Solver::Impl::HeldVertices(
    const Frame& frame, const Points& linear, std::optional<internal::AnchorMotion>* motion) const {
  const Rig& rig = *rig_;
  std::vector<std::pair<int, Eigen::Vector3d>> held;
  for (int v : rig.fixed_vertices()) held.emplace_back(v, linear.row(v).transpose());
  if (rig.boundary_mode() == BoundaryMode::kAnchored) {
    *motion = internal::BlendAnchorMotions(rig.internals().anchor_motions, frame.weights);
    for (int v : rig.anchor_vertices()) {
      held.emplace_back(v, (*motion)->Apply(rig.shape(0).row(v).transpose(), rig.anchor_centroid()));
    }
  }
  for (const Pin& pin : frame.pins) held.emplace_back(pin.vertex, pin.position);
  return held;
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
  std::vector<double> rest_lengths;
  BlendRestLengths(rig, frame.weights, &rest_lengths);
  springs_.SetRestLengths(std::move(rest_lengths), rig.spring_kind(), internal::KindStiffness(rig.options()),
                          internal::StiffnessFloor(rig));

  std::optional<internal::AnchorMotion> motion;
  const auto held = HeldVertices(frame, linear, &motion);
  std::vector<Eigen::Vector3d> held_points;
  for (const auto& h : held) held_points.push_back(h.second);
  BoundaryMode mode = rig.boundary_mode();
  if (mode != BoundaryMode::kAnchored && mode != BoundaryMode::kFixedVertices) {
    mode = internal::SpansRigidly(held_points, diagonal) ? BoundaryMode::kFixedVertices
           : held.empty()                                ? BoundaryMode::kFloating
                                                         : BoundaryMode::kPartiallyFixed;
  }
  if (options_.warm_start) {
    predictor_.Predict(linear, motion, rig.anchor_centroid(), frame.weights, held, options_.extrapolate,
                       [&](const Eigen::VectorXd& x) { return springs_.Energy(x); }, &x_);
  } else {
    x_.resize(3 * n);
    for (int v = 0; v < n; ++v) x_.segment<3>(3 * v) = linear.row(v).transpose();
  }
  std::fill(held_.begin(), held_.end(), 0);
  for (const auto& [v, p] : held) {
    x_.segment<3>(3 * v) = p;
    held_[3 * v] = held_[3 * v + 1] = held_[3 * v + 2] = 1;
  }
  summary.fixed_vertices = static_cast<int>(std::count(held_.begin(), held_.end(), 1) / 3);
  double diagonal_shift = 0.0;
  if (mode == BoundaryMode::kFloating) {
    // 3-2-1 gauge: any configuration can be moved so, hence it removes the rigid motions without a force.
    if (!internal::HoldGauge(rig.gauge_vertices(), &x_, &held_)) {
      summary.termination = Termination::kNumericalFailure;
      summary.message = "the gauge vertices became collinear in the start configuration";
      summary.solve_ms = Elapsed(start);
      return summary;
    }
  } else if (mode == BoundaryMode::kPartiallyFixed) {
    diagonal_shift = 1e-8 / rig.summary().mean_rest_length;
  }

  base_held_ = held_;
  contacts_.Clear();
  internal::MinimizerSummary minimized;
  Minimize(diagonal_shift, &minimized);
  int contact_rounds = 0;
  if (!colliders_.empty() && minimized.termination != internal::MinimizerTermination::kNumericalFailure) {
    // Paper section 4: hold the vertices that went inside an obstacle on its surface and solve again, and
    // let go of held ones the springs pull away from it, until nothing changes.
    std::vector<RigidTransform> motions(colliders_.size());
    if (!frame.collider_transforms.empty()) motions = frame.collider_transforms;
    const double offset = options_.contact_offset * diagonal;
    const internal::Curvature curvature{1.0, options_.hessian == HessianMode::kAbsolute};
    while (true) {
      springs_.Evaluate(x_, held_, curvature);
      if (!contacts_.Update(colliders_, motions, springs_.reaction(), rig.num_surface_vertices(), offset,
                            10.0 * options_.residual_tolerance, base_held_, &x_, &held_)) {
        break;
      }
      if (contact_rounds == options_.max_contact_rounds) {
        minimized.termination = internal::MinimizerTermination::kMaxIterations;
        minimized.message = fmt::format("contacts still changing after {} rounds", options_.max_contact_rounds);
        break;
      }
      ++contact_rounds;
      Minimize(diagonal_shift, &minimized);
      if (minimized.termination == internal::MinimizerTermination::kNumericalFailure) break;
    }
    summary.contacts = static_cast<int>(contacts_.contacts().size());
  }
  summary.contact_rounds = contact_rounds;
  summary.termination = ToTermination(minimized.termination);
  summary.message = minimized.message;
  summary.newton_iterations = minimized.iterations;
  summary.factorizations = minimized.factorizations;
  summary.projected_factorizations = minimized.projected_factorizations;
  summary.shifted_factorizations = minimized.shifted_factorizations;
  summary.line_search_halvings = minimized.line_search_halvings;
  summary.cg_iterations = minimized.cg_iterations;
  summary.initial_residual = minimized.initial_residual;
  summary.residual = minimized.residual;
  summary.last_step = minimized.last_step;
  summary.energy = minimized.energy;
  summary.factorize_ms = minimized.factorize_ms;

  summary.inverted_tetrahedra = internal::CountInvertedTetrahedra(rig.tetrahedra(), x_);
  Points solved(n, 3);
  for (int v = 0; v < n; ++v) solved.row(v) = x_.segment<3>(3 * v).transpose();
  if (mode == BoundaryMode::kFloating) {
    internal::AlignRigidly(linear.topRows(rig.num_surface_vertices()), &solved);
  }
  if (summary.termination != Termination::kNumericalFailure) {
    // A frame that did not converge is a warm start, but no node for the predictor.
    predictor_.Add(solved, motion, frame.weights, summary.converged());
    previous_ = solved;
  } else {
    predictor_.Reset();  // never warm-start from a broken state
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

SolveSummary Solver::Solve(const Frame& frame, Points* positions) { return impl_->Solve(frame, positions); }
void Solver::Reset() { impl_->Reset(); }
void Solver::SetWarmStart(const Points& all_vertices) { impl_->SetWarmStart(all_vertices); }
void Solver::SetColliders(std::vector<Collider> colliders) { impl_->SetColliders(std::move(colliders)); }
const Points& Solver::all_positions() const { return impl_->all_positions(); }
const Rig& Solver::rig() const { return *impl_->rig_; }
const SolveOptions& Solver::options() const { return impl_->options_; }
void Solver::set_options(const SolveOptions& options) { impl_->SetOptions(options); }

}  // namespace springblend
