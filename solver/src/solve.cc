// The per-frame solve: blend the rest lengths, hold the frame's boundary conditions (fixed vertices, the
// anchor's blended motion, pins, a gauge), start from the rig's prediction for the weights, minimize, and
// repeat around the contact active set (paper sections 3.2-3.4 and 4). Nothing carries over from one frame
// to the next but buffers: the kept factorization and the minimizer's state are reset per frame.
#include "springblend/solve.h"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <optional>

#include "anchor.h"
#include "boundary_conditions.h"
#include "contact_set.h"
#include "linear_system.h"
#include "local_finish.h"
#include "minimizer.h"
#include "mix.h"
#include "frame_conditions.h"
#include "laplacian.h"
#include "target_paths.h"
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
  m.type = o.method == SolveMethod::kLbfgs ? internal::MinimizerType::kLbfgs : internal::MinimizerType::kInexactNewton;
  m.preconditioner = o.method == SolveMethod::kNewtonLaplacian ? internal::Preconditioner::kLaplacian
                                                              : internal::Preconditioner::kKeptFactor;
  m.lbfgs_history = o.lbfgs_history;
  m.lbfgs_max_iterations = o.lbfgs_max_iterations;
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
    case internal::MinimizerTermination::kCancelled: return Termination::kCancelled;
  }
  return Termination::kNumericalFailure;
}

// A path frame takes its span step before the local finish when more than this share of its free vertices is
// out of balance at the start, else only once the local finish gave up (SolveOptions::path_span_step). On the
// face's jawOpen path (bench/paths_bench.cc, 17 off-sample frames): at the default 32 steps per unit the same
// 15 frames finish locally either way (4.6 against 4.3 ms median); at 16 steps per unit 12 against 12, 10.8
// against 30.3 ms median (local regions of 700-1300 vertices shrink to 36-362); the step first for every
// frame: 13, 15-17 ms median (its Hessian products cost more than a small region).
constexpr double kSpanFirstShare = 0.01;

}  // namespace

class Solver::Impl {
 public:
  Impl(std::shared_ptr<const Rig> rig, SolveOptions options)
      : rig_(std::move(rig)),
        options_(std::move(options)),
        springs_(internal::TopologyOf(*rig_)),
        linear_(rig_->internals().pattern->matrix, *rig_->internals().cholesky, rig_->options().linear_solver) {
    ValidateOptions(*rig_, options_);
    minimizer_ = internal::Minimizer::Create(ToMinimizerOptions(options_));
    springs_.set_length_scale(rig_->summary().mean_rest_length);
    held_.assign(3 * static_cast<size_t>(rig_->num_vertices()), 0);
  }

  SolveSummary Solve(const Frame& frame, Points* positions, const std::function<bool()>* stop);
  // The start for these target weights (stacked 3n) from the linear blend of every simulated vertex.
  void StartOf(const Points& linear, const std::vector<double>& weights,
               const std::optional<internal::AnchorMotion>& motion, Eigen::VectorXd* x) const {
    const int n = static_cast<int>(linear.rows());
    x->resize(3 * n);
    for (int v = 0; v < n; ++v) x->segment<3>(3 * v) = linear.row(v).transpose();
    if (options_.use_target_paths) internal::AddPathCorrections(rig_->internals().paths, weights, motion, x);
  }
  const Points& all_positions() const { return previous_; }
  void SetColliders(std::vector<Collider> colliders) {
    if (!colliders.empty() && rig_->boundary_mode() == BoundaryMode::kFloating) {
      throw Error(ErrorCode::kInvalidInput,
                  "colliders need a rig held by fixed vertices or an internal anchor; this rig has neither "
                  "(give it fixed vertices, hold an open surface's outer rim with hold_outer_rim / "
                  "--hold-outer-rim, or give it an interior so it gets an anchor)");
    }
    colliders_ = std::move(colliders);
  }
  void SetOptions(const SolveOptions& options) {
    ValidateOptions(*rig_, options);
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
  // The Laplacian of the rest stiffness, with the always-held vertices eliminated; built on first use.
  internal::LaplacianPreconditioner* Laplacian() {
    if (options_.method == SolveMethod::kNewton) return nullptr;
    if (!laplacian_) {
      const Rig& rig = *rig_;
      std::vector<double> rest_lengths;
      internal::BlendRestLengths(rig, std::vector<double>(rig.num_shapes(), 0.0), &rest_lengths);
      internal::SpringSystem rest(internal::TopologyOf(rig));
      rest.SetRestLengths(std::move(rest_lengths), rig.spring_kind(), internal::KindStiffness(rig.options()),
                          internal::StiffnessFloor(rig));
      std::vector<int> always = rig.fixed_vertices();
      if (rig.boundary_mode() == BoundaryMode::kAnchored) {
        always.insert(always.end(), rig.anchor_vertices().begin(), rig.anchor_vertices().end());
      }
      laplacian_ = std::make_unique<internal::LaplacianPreconditioner>(internal::TopologyOf(rig), rest.stiffness(),
                                                                        always, rig.options().linear_solver);
    }
    return laplacian_.get();
  }

  void Minimize(double diagonal_shift, internal::MinimizerSummary* summary) {
    internal::MinimizerProblem problem;
    problem.laplacian = Laplacian();
    problem.timing = &timing_;
    problem.stop = stop_;
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
  std::unique_ptr<internal::LaplacianPreconditioner> laplacian_;
  internal::MinimizerTiming timing_;
  const std::function<bool()>* stop_ = nullptr;  // this frame's stop check (Solve)
  internal::ContactSet contacts_;
  std::vector<Collider> colliders_;
  std::vector<char> held_, base_held_;  // held coordinates of this frame, and before contacts
  Eigen::VectorXd x_;
  Points previous_;  // the last solution (all_positions)
};

SolveSummary Solver::Impl::Solve(const Frame& frame, Points* positions, const std::function<bool()>* stop) {
  const auto start = std::chrono::steady_clock::now();
  stop_ = stop;
  const Rig& rig = *rig_;
  SolveSummary summary;
  const int n = rig.num_vertices();
  const double diagonal = rig.summary().bounding_box_diagonal;
  ValidateFrame(rig, frame, colliders_.size());
  // Everything below blends per sculpted shape (in-betweens, combinations): their weights, once.
  const std::vector<double> shape_weights = rig.ShapeWeights(frame.weights);
  const Points linear = internal::LinearBlendShapes(rig, shape_weights);
  summary.pins = static_cast<int>(frame.pins.size());
  if (options_.linear) {
    *positions = linear.topRows(rig.num_surface_vertices());
    summary.finish = Finish::kNone;
    summary.termination = Termination::kLinear;
    summary.message = "linear blendshape";
    summary.solve_ms = Elapsed(start);
    return summary;
  }
  // A mix under the superposed model rests at its prediction (mix.h); every other frame at the paper's lengths.
  const std::vector<char> linear_targets = internal::LinearTargets(rig, options_);
  const bool superposed = internal::IsSuperposedMix(options_, linear_targets, frame.weights);
  std::vector<double> rest_lengths;
  Eigen::VectorXd prediction;
  if (superposed) {
    const auto mix_start = std::chrono::steady_clock::now();
    internal::Prediction(rig, frame.weights, linear_targets, options_.use_target_paths, &prediction);
    summary.mix_strain_share = internal::SuperposedRestLengths(rig, frame.weights, linear_targets,
                                                               options_.use_target_paths, prediction, &rest_lengths);
    summary.mix_ms = Elapsed(mix_start);
  } else {
    internal::BlendRestLengths(rig, shape_weights, &rest_lengths);
  }
  springs_.SetRestLengths(std::move(rest_lengths), rig.spring_kind(), internal::KindStiffness(rig.options()),
                          internal::StiffnessFloor(rig));

  std::vector<std::pair<int, Eigen::Vector3d>> pins;
  for (const Pin& pin : frame.pins) pins.emplace_back(pin.vertex, pin.position);
  const internal::FrameConditions conditions = internal::ConditionsOf(rig, shape_weights, linear, pins);
  const BoundaryMode mode = conditions.mode;
  if (superposed) {
    x_ = std::move(prediction);  // the springs' rest state but for the averaged strains: the answer is next to it
  } else {
    StartOf(linear, frame.weights, conditions.motion, &x_);
  }
  if (!internal::HoldConditions(rig, conditions, &x_, &held_)) {
    summary.termination = Termination::kNumericalFailure;
    summary.message = "the gauge vertices became collinear in the start configuration";
    summary.solve_ms = Elapsed(start);
    return summary;
  }
  if (!superposed && options_.use_target_paths && options_.scale_mix_start &&
      internal::IsPathMix(rig.internals().paths, frame.weights)) {
    Eigen::VectorXd base(x_.size());  // only for mixes: a path frame's start is ready in milliseconds
    for (Eigen::Index d = 0; d < x_.size(); ++d) base[d] = held_[d] ? x_[d] : linear(d / 3, d % 3);
    summary.mix_start_scale = internal::ScaleMixStart(
        rig.internals().paths, frame.weights, base, [&](const Eigen::VectorXd& y) { return springs_.Energy(y); }, &x_);
  }
  {
    std::vector<int> vertices;
    for (const auto& h : conditions.held) vertices.push_back(h.first);
    std::sort(vertices.begin(), vertices.end());
    summary.fixed_vertices = static_cast<int>(std::unique(vertices.begin(), vertices.end()) - vertices.begin());
  }
  const double diagonal_shift = conditions.diagonal_shift;
  // Nothing learnt from an earlier frame may change this one.
  linear_.DropFactor();
  minimizer_->Reset();
  timing_ = {};

  base_held_ = held_;
  contacts_.Clear();
  internal::MinimizerSummary minimized;
  bool finished = false;
  if (options_.local_finish) {
    internal::LocalFinishOptions local;
    local.residual_tolerance = options_.residual_tolerance;
    local.step_tolerance = options_.step_tolerance;
    local.max_step_fraction = options_.max_step_fraction;
    local.max_line_search_steps = options_.max_line_search_steps;
    local.max_share = options_.local_finish_share;
    // The region's steps are direct solves, in double precision.
    local.linear_solver = internal::RegionLinearSolver(rig.options().linear_solver);
    // The span step: first where the start is out of balance at many vertices (a local region that large
    // costs more than the step: the local finish gives up at once), else once a local finish gave up; the
    // second try starts from the frame's start again (a region a try left part way to balance has forces
    // below the tolerance but not its error).
    const bool span = !superposed && options_.use_target_paths && options_.path_span_step &&
                      internal::HasPathSpan(rig.internals().paths, frame.weights);
    const Eigen::VectorXd frame_start = span ? x_ : Eigen::VectorXd();
    for (int attempt = 0; attempt < 2 && !finished; ++attempt) {
      internal::LocalFinishOptions here = local;
      if (attempt == 0 && span) here.max_seed_share = kSpanFirstShare;
      if (attempt == 1) {
        if (!span) break;
        if (stop != nullptr && *stop && (*stop)()) break;
        const Eigen::VectorXd given_up = x_;
        x_ = frame_start;
        const auto clock = std::chrono::steady_clock::now();
        summary.span_vectors = internal::RefineInPathSpan(rig.internals().paths, frame.weights, conditions.motion,
                                                          options_.residual_tolerance, &springs_, held_,
                                                          diagonal_shift, &x_);
        timing_.spring_ms += Elapsed(clock);
        if (summary.span_vectors == 0) {
          x_ = given_up;  // the full solve goes on from the lower energy
          break;
        }
      }
      const auto clock = std::chrono::steady_clock::now();
      const internal::LocalFinishResult result = internal::LocalFinish(
          &springs_, held_, diagonal_shift, diagonal, rig.summary().mean_rest_length, here, stop, &x_);
      timing_.solve_ms += Elapsed(clock);
      summary.free_vertices = result.free_vertices;
      if (attempt == 0) minimized.initial_residual = result.initial_residual;
      minimized.iterations += result.iterations;
      minimized.line_search_halvings += result.line_search_halvings;
      if (result.converged) {
        finished = true;
        summary.finish = Finish::kLocal;
        summary.solved_vertices = result.vertices;
        summary.local_finish_note.clear();
        minimized.termination = internal::MinimizerTermination::kConverged;
        minimized.residual = result.residual;
        minimized.last_step = result.last_step;
        minimized.energy = springs_.Energy(x_);
      } else {
        summary.local_finish_note = result.why;
      }
    }
  }
  if (!finished) {
    Minimize(diagonal_shift, &minimized);  // keeps the initial residual once iterations were counted
    summary.finish = Finish::kFull;
    if (!options_.local_finish) {
      for (int v = 0; v < n; ++v) summary.free_vertices += !(base_held_[3 * v] && base_held_[3 * v + 1] && base_held_[3 * v + 2]);
    }
    summary.solved_vertices = summary.free_vertices;
  }
  int contact_rounds = 0;
  if (!colliders_.empty() && minimized.termination != internal::MinimizerTermination::kNumericalFailure) {
    // Paper section 4: hold the vertices that went inside an obstacle on its surface and solve again, and
    // let go of held ones the springs pull away from it, until nothing changes.
    std::vector<RigidTransform> motions(colliders_.size());
    if (!frame.collider_transforms.empty()) motions = frame.collider_transforms;
    const double offset = options_.contact_offset * diagonal;
    const internal::Curvature curvature{1.0, options_.hessian == HessianMode::kAbsolute};
    while (minimized.termination != internal::MinimizerTermination::kCancelled) {
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
  summary.lbfgs_iterations = minimized.lbfgs_iterations;
  summary.newton_fallbacks = minimized.newton_fallbacks;
  summary.spring_ms = timing_.spring_ms;
  summary.linear_solve_ms = timing_.solve_ms;
  summary.line_search_ms = timing_.line_search_ms;

  if (options_.certify_minimum && summary.termination == Termination::kConverged) {
    // The true Hessian (no curvature clamped, no Levenberg-Marquardt shift beyond the frame's own gauge shift)
    // on the coordinates free at the answer, contacts held as they end: positive definite means a strict minimum.
    const auto certify_start = std::chrono::steady_clock::now();
    std::vector<double> values(springs_.topology().pattern->matrix.row_indices.size());
    springs_.Assemble(x_, held_, internal::Curvature{1.0, false}, diagonal_shift, &values);
    linear_.Select(held_);
    const internal::FactorStatus status = linear_.Factorize(values);
    linear_.DropFactor();
    summary.minimum = status == internal::FactorStatus::kOk                    ? MinimumCheck::kMinimum
                      : status == internal::FactorStatus::kNotPositiveDefinite ? MinimumCheck::kNotMinimum
                                                                               : MinimumCheck::kNotChecked;
    summary.certify_ms = Elapsed(certify_start);
  }
  summary.inverted_tetrahedra = internal::CountInvertedTetrahedra(rig.tetrahedra(), x_);
  Points solved(n, 3);
  for (int v = 0; v < n; ++v) solved.row(v) = x_.segment<3>(3 * v).transpose();
  if (mode == BoundaryMode::kFloating) {
    internal::AlignRigidly(linear.topRows(rig.num_surface_vertices()), &solved);
  }
  previous_ = solved;
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

SolveSummary Solver::Solve(const Frame& frame, Points* positions) { return impl_->Solve(frame, positions, nullptr); }
SolveSummary Solver::Solve(const Frame& frame, Points* positions, const std::function<bool()>& stop) {
  return impl_->Solve(frame, positions, &stop);
}
Points Solver::Start(const std::vector<double>& weights) const {
  const Rig& rig = *impl_->rig_;
  ValidateWeights(rig, weights);
  const std::vector<double> shape_weights = rig.ShapeWeights(weights);
  const Points linear = internal::LinearBlendShapes(rig, shape_weights);
  std::optional<internal::AnchorMotion> motion;
  if (rig.boundary_mode() == BoundaryMode::kAnchored) {
    motion = internal::BlendAnchorMotions(rig.internals().anchor_motions, shape_weights);
  }
  Eigen::VectorXd x;
  const SolveOptions& options = impl_->options_;
  const std::vector<char> linear_targets = internal::LinearTargets(rig, options);
  const bool superposed = !options.linear && internal::IsSuperposedMix(options, linear_targets, weights);
  if (superposed) {
    internal::Prediction(rig, weights, linear_targets, options.use_target_paths, &x);
  } else {
    impl_->StartOf(linear, weights, motion, &x);
  }
  if (options.use_target_paths && options.scale_mix_start && !options.linear && !superposed &&
      internal::IsPathMix(rig.internals().paths, weights)) {
    // The solve's walk along the corrections' ray, with every vertex free (the held ones are placed later).
    internal::SpringSystem springs(internal::TopologyOf(rig));
    springs.set_length_scale(rig.summary().mean_rest_length);
    std::vector<double> rest_lengths;
    internal::BlendRestLengths(rig, shape_weights, &rest_lengths);
    springs.SetRestLengths(std::move(rest_lengths), rig.spring_kind(), internal::KindStiffness(rig.options()),
                           internal::StiffnessFloor(rig));
    Eigen::VectorXd base(x.size());
    for (Eigen::Index d = 0; d < x.size(); ++d) base[d] = linear(d / 3, d % 3);
    internal::ScaleMixStart(rig.internals().paths, weights, base,
                            [&](const Eigen::VectorXd& y) { return springs.Energy(y); }, &x);
  }
  Points start(rig.num_vertices(), 3);
  for (int v = 0; v < rig.num_vertices(); ++v) start.row(v) = x.segment<3>(3 * v).transpose();
  return start;
}
void Solver::SetColliders(std::vector<Collider> colliders) { impl_->SetColliders(std::move(colliders)); }
const Points& Solver::all_positions() const { return impl_->all_positions(); }
std::int64_t Solver::bytes() const { return BytesFor(*impl_->rig_, impl_->options_); }

std::int64_t Solver::BytesFor(const Rig& rig, const SolveOptions& options) {
  // Measured (glibc's heap after one frame, bench meshes of 471 to 13k vertices): 124-127 bytes per spring
  // from the start, 8.6-10 bytes per entry of the full system's factor once factored (values, CHOLMOD's
  // supernodal indices); frames that hold many vertices factor a smaller system beside it (Select), hence
  // 16. L-BFGS keeps its history; the Laplacian-preconditioned method factors the Laplacian (a third of
  // the unknowns) instead, about 14 bytes per Hessian entry in all. Linear frames factor nothing.
  const std::int64_t n = rig.num_vertices(), springs = rig.num_springs();
  const std::int64_t vertex = 3 * static_cast<std::int64_t>(sizeof(double)) * n;  // one #V x 3 array
  if (options.linear) return 128 * springs + 4 * vertex;
  const std::int64_t factor = rig.internals().cholesky->FactorNonzeros();
  const std::int64_t hessian = rig.summary().hessian_nonzeros;
  std::int64_t bytes = 160 * springs + 16 * vertex;
  if (options.method == SolveMethod::kNewtonLaplacian) {
    bytes += 20 * hessian;
  } else {
    bytes += 16 * factor;
  }
  if (options.method == SolveMethod::kLbfgs) {
    bytes += 2 * static_cast<std::int64_t>(options.lbfgs_history) * vertex + 2 * factor;
  }
  return bytes;
}

const Rig& Solver::rig() const { return *impl_->rig_; }
const SolveOptions& Solver::options() const { return impl_->options_; }
void Solver::set_options(const SolveOptions& options) { impl_->SetOptions(options); }

}  // namespace springblend
