// The per-frame solve: blend the rest lengths with a weight vector and find the equilibrium of the
// blended mass-spring system by Newton's method (paper sections 3.2-3.3). A frame's answer is a function of
// the rig and that frame alone (weights, pins, colliders and their motion, options): every solve starts from
// the rig's deterministic prediction for its weights (the linear blend plus each target's precomputed
// physical correction, see RigOptions::target_paths), never from an earlier frame. A Solver only keeps
// buffers between frames, which make no frame different.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "springblend/collider.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"

namespace springblend {

// One frame's request. weights has one entry per target, in the rig's target order; the rest shape takes
// the remainder 1 - sum(weights). That covers the paper's two-shape alpha ({alpha}), a convex combination
// of many shapes, and the delta weights of face rigs. Weights outside [0, 1] are allowed.
struct Pin {
  int vertex = -1;  // a simulated vertex: a mesh vertex (0-based), or an interior one (Rig::shape rows)
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
};

struct Frame {
  std::vector<double> weights;
  // Vertices dragged to a position for this frame (paper Fig. 5): boundary conditions like fixed vertices.
  std::vector<Pin> pins;
  // The colliders' motion in this frame, one per collider of the Solver (empty: none moves).
  std::vector<RigidTransform> collider_transforms;
};

enum class HessianMode {
  kTrueWithProjectedFallback,  // use the true Hessian while its Cholesky succeeds, else the projected one
  kProjected,                  // always clamp each spring's transverse term at zero (always SPD)
  kAbsolute,                   // replace a negative transverse term by its absolute value (always SPD)
};
const char* ToString(HessianMode mode);

// How a frame's equilibrium is found (all reach the same equilibrium from the same start, to the tolerances).
enum class SolveMethod {
  // Inexact Newton: conjugate gradients preconditioned by a 3n x 3n factorization of the Hessian, kept
  // across the frame's Newton iterations and refactored when it stops paying off.
  kNewton,
  // Newton-CG preconditioned by the scalar n x n Laplacian of the rest stiffness (a ninth of the factor,
  // factorized once per solver); falls back to a 3n factorization only when CG finds no direction.
  kNewtonLaplacian,
  // L-BFGS with the Laplacian as its initial Hessian (Liu et al. 2017), finished by inexact Newton on a
  // stall or after lbfgs_max_iterations.
  kLbfgs,
};
const char* ToString(SolveMethod method);
SolveMethod SolveMethodFromString(const std::string& name);  // "newton" | "newton-laplacian" | "lbfgs"

// How a frame that moves several targets combines them (a frame that moves one target is the paper's in both;
// solver/src/mix.h has the formulas).
enum class MixModel {
  // The frame's prediction is the linear blend plus the targets' own physical corrections at their weights (each
  // its path, the target alone) averaged per vertex by their magnitudes, and its springs rest at that
  // prediction's lengths, plus the targets' residual strains only while one target dominates the frame: deltas
  // add as vectors, each target keeps its own correction (a jaw's rotation) where it alone corrects, and neither
  // length changes nor corrections add up. Faithful where captured faces move 20-40 expressions at once, and
  // there the prediction is the answer (energy zero, no Newton step). Correctives (linear_targets) add as linear
  // deltas.
  kSuperposed,
  // The paper's blend (section 3.3): r̄_q = r_q^0 + sum_t w_t (r_q^t - r_q^0), every target's length change
  // added up. Where many targets move the same springs (a mouth) the mix buckles into a shape none of them has.
  kRestLengths,
};
const char* ToString(MixModel model);
// The targets SolveOptions::linear_targets names when it is not given: ARKit's correctives (Apple's ARKit face
// tracking defines mouthClose as closing the lips whatever the jaw does: a corrective of jawOpen).
inline const std::vector<std::string> kDefaultCorrectives = {"mouthClose"};
MixModel MixModelFromString(const std::string& name);  // "superposed" | "rest-lengths"

struct SolveOptions {
  SolveMethod method = SolveMethod::kNewton;
  // How several targets combine (MixModel).
  MixModel mix = MixModel::kSuperposed;
  // With MixModel::kSuperposed: targets that are correctives rather than shapes of their own (sculpted to be added
  // to others), added as linear deltas: no physical correction of their own, no residual strain; a frame that
  // moves one of them alone is its linear blend. Names, matched case-insensitively. Nullopt: the targets
  // kDefaultCorrectives names, where the rig has them (ARKit's mouthClose closes the lips of an open jaw and is
  // meant to be added to jawOpen; alone it pushes the lips through each other, and its physical answer at 0.19 is
  // 1.6 % of the face's diagonal from its sculpt's blend). A given list must name targets of the rig.
  std::optional<std::vector<std::string>> linear_targets;
  // kLbfgs: (s, y) pairs kept [1, 100], and iterations before Newton takes over [1, 10000].
  int lbfgs_history = 10;
  int lbfgs_max_iterations = 100;
  // Converged when the largest force on any free degree of freedom is at most this. Forces are in units of
  // strain (k = 1 / rest length), so the tolerance does not depend on the mesh's scale. Range (0, 1).
  double residual_tolerance = 1e-6;
  // ...and the last Newton step (largest coordinate change) was at most this fraction of the bounding-box
  // diagonal. Both must hold: where the system is soft a small force alone does not mean a small error.
  double step_tolerance = 1e-5;
  // Newton iterations per frame before giving up (the frame then reports kMaxIterations). Range [1, 10000].
  int max_iterations = 200;
  // Backtracking line search halvings per Newton step. Range [1, 60].
  int max_line_search_steps = 40;
  HessianMode hessian = HessianMode::kTrueWithProjectedFallback;
  // Reuse a numeric factorization across Newton iterations and frames: each Newton step is then solved by
  // conjugate gradients preconditioned with the last factorization (inexact Newton, method.md section 4),
  // and the Hessian is refactored only when that stops paying off. false: a fresh factorization and a
  // direct solve in every Newton iteration (the paper's method; the benchmark's baseline).
  bool reuse_factorization = true;
  // Conjugate-gradient iterations per Newton step before giving up on the old factorization and
  // refactoring. Range [1, 10000].
  int max_cg_iterations = 40;
  // Refactor before the next Newton step when the conjugate gradients of this one cost more than this
  // fraction of a factorization (costs from the symbolic analysis's flop counts, so the decision, and the
  // result, do not depend on the machine's load). Range (0, 100].
  double refactor_cost_ratio = 0.5;
  // With reuse_factorization: where the conjugate gradients meet negative curvature of the true Hessian (a
  // saddle: a buckling lip, a compressed fold), add that direction to the projected Newton step, downhill and
  // as long as a step may be, for the line search to shorten. A saddle is then left in a few iterations
  // instead of crept off over dozens (face-mix's 36-frame sweep: the worst frame 36 -> 12 Newton iterations,
  // the mean 7.1 -> 6.3). Where the mix has several minima a frame may settle on another one than without it
  // (one frame of those 36, 1.2e-4 of the diagonal away); the answer is still the frame's alone, a certified
  // minimum where checked, and continuous along sweeps (docs/benchmark.md). false: the projected step alone.
  bool follow_negative_curvature = true;
  // No vertex moves further than this fraction of the mean rest length in one Newton step, so a step
  // cannot carry a vertex through its neighbours into an inverted equilibrium. Range (0, 1000].
  double max_step_fraction = 2.0;
  // Start from the rig's target paths (the linear blend plus each target's physical correction at its
  // weight). false: from the linear blendshape alone (slower, and a frame may land on another equilibrium
  // where thin parts can buckle either way). Either way the answer depends on the frame alone.
  bool use_target_paths = true;
  // Finish a frame where its start is out of balance only (Newton on those vertices and rings around them,
  // the rest held at the start, grown until every free force is within the tolerance), then the full
  // convergence test; a full solve when that region outgrows local_finish_share of the vertices or does not
  // converge. Single-target frames start on their certified path and finish in milliseconds; a mix frame
  // whose start is out of balance nearly everywhere costs one force pass more. Range of the share (0, 1].
  bool local_finish = true;
  double local_finish_share = 0.15;
  // A frame that moves one target (its in-betweens included) and that the local finish gives up on, or that
  // starts out of balance at more than 1 % of its free vertices, takes one Newton step in the span of its
  // path's samples and exact tangents around its weight (two samples either side of its interval on the path's
  // smooth piece), the lowest energy there: a Galerkin projection of the frame's equilibrium onto the path's
  // own vectors, much closer to it than the interpolant. The local finish is then tried (again, from the
  // frame's start) before a full solve (face jawOpen: 15 of 17 off-sample frames finished locally against 13).
  // Costs about one Hessian product per vector; only ever lowers the energy.
  bool path_span_step = true;
  // A frame that moves two or more targets starts on the ray from the linear blend through the sum of their
  // path corrections, at the lowest energy met walking down from the full sum in steps of 1/8 (then one
  // parabolic step): the corrections overshoot where targets move the same parts (horse random mixes: the
  // start's energy 6.1 against 0.52 at s = 0.53, CG iterations per frame 81 to 58). A function of the frame
  // alone; SolveSummary::mix_start_scale reports the s taken. Costs an energy pass per grid step.
  bool scale_mix_start = true;
  // Contact rounds per frame (solve, catch penetrating vertices, solve again) before giving up. [1, 1000]
  int max_contact_rounds = 30;
  // Contact vertices are held this fraction of the diagonal outside the obstacle's surface. [0, 0.01]
  double contact_offset = 1e-6;
  // The solution of a frame is the equilibrium; with `linear` the solver returns the plain linear
  // blendshape instead (for comparison) and does no Newton iteration.
  bool linear = false;
  // Certify a converged frame's answer as a local minimum: one Cholesky factorization of the true Hessian on
  // the free coordinates at the answer (SolveSummary::minimum). Where a frame has several equilibria, an answer
  // is right when it is a minimum, whichever one; this says so per frame. Costs about one factorization.
  bool certify_minimum = false;

  void Validate() const;  // throws Error(kInvalidInput) naming the field
};

// Whether a frame's answer is a local minimum of the energy (SolveOptions::certify_minimum).
enum class MinimumCheck {
  kNotChecked,  // not asked, or the frame did not converge
  kMinimum,     // the true Hessian on the free coordinates is positive definite there: a strict local minimum
  kNotMinimum,  // it is not: a saddle or a flat direction of the energy, not an answer to keep
};
const char* ToString(MinimumCheck check);

// How a frame was finished.
enum class Finish {
  kFull,   // Newton on every free vertex
  kLocal,  // Newton only where the start was out of balance (SolveOptions::local_finish); none if it was not
  kNone,   // no solve (SolveOptions::linear)
};
const char* ToString(Finish finish);

enum class Termination {
  kConverged,      // residual below tolerance
  kMaxIterations,  // iteration cap reached; positions are the last iterate
  kStalled,        // the line search could not lower the energy any more before the residual got small
  kNumericalFailure,  // a factorization failed or a value became non-finite; positions are the start
  kLinear,         // linear blendshape requested: no solve
  kCancelled,      // the stop check (Solver::Solve's `stop`) said stop; positions are the last iterate
};
const char* ToString(Termination termination);

struct SolveSummary {
  Termination termination = Termination::kNumericalFailure;
  std::string message;
  int newton_iterations = 0;
  int factorizations = 0;
  int projected_factorizations = 0;  // factorizations with compressed springs' curvature reduced
  int shifted_factorizations = 0;    // factorizations that needed a Levenberg-Marquardt diagonal shift
  int line_search_halvings = 0;
  int cg_iterations = 0;   // preconditioned conjugate-gradient iterations (reuse_factorization)
  double initial_residual = 0.0;
  double residual = 0.0;  // final largest force on a free degree of freedom (strain units)
  double last_step = 0.0;  // last Newton step's largest coordinate change, fraction of the diagonal
  double energy = 0.0;    // final spring energy
  int fixed_vertices = 0;      // boundary conditions in this frame: fixed, anchor and pinned vertices
  int pins = 0;
  int contacts = 0;        // mesh vertices held on an obstacle's surface at the end of the frame
  int contact_rounds = 0;  // extra solves the contacts took
  int inverted_tetrahedra = 0;  // tetrahedra turned inside out in the solution (paper section 5's limit)
  int lbfgs_iterations = 0;  // kLbfgs: its own iterations (newton_iterations counts them too)
  int newton_fallbacks = 0;  // kLbfgs: 1 when Newton finished the frame
  Finish finish = Finish::kFull;
  MinimumCheck minimum = MinimumCheck::kNotChecked;
  double certify_ms = 0.0;  // the certificate's factorization (part of solve_ms)
  int solved_vertices = 0;  // vertices Newton moved: the local region, or every free vertex
  int free_vertices = 0;    // vertices with a free coordinate in this frame
  std::string local_finish_note;  // why a local finish gave up (then the frame was solved in full)
  double mix_start_scale = 1.0;  // where a mix frame started on its corrections' ray (SolveOptions::scale_mix_start)
  int span_vectors = 0;  // dimension of the path span the frame stepped in (SolveOptions::path_span_step; 0: none)
  double solve_ms = 0.0;
  // Where solve_ms went: spring passes (energy, forces, Hessian blocks), linear solves (conjugate gradients
  // with their Hessian products and preconditioner, direct solves), line searches, factorizations.
  double spring_ms = 0.0;
  double linear_solve_ms = 0.0;
  double line_search_ms = 0.0;
  double factorize_ms = 0.0;
  double mix_ms = 0.0;  // the superposed mix's prediction and rest lengths (MixModel::kSuperposed; part of solve_ms)
  // The share of its targets' residual strains a superposed mix carried (1: one target dominates, as in its own
  // frame; 0: the springs rest at the prediction, which is the answer unless colliders or pins move it).
  double mix_strain_share = 0.0;

  bool converged() const {
    return termination == Termination::kConverged || termination == Termination::kLinear;
  }
};

// Bounds of a frame's weights, beyond which the blended shape overflows (answers are float32): each target's
// weight, and a combination's (the product of its drivers' weights), within +-kMaxTargetWeight; the effective
// weight of every other sculpted shape (in-betweens extrapolate with their last segment's slope, at most
// 1 / kMinInbetweenSpacing) within +-kMaxShapeWeight.
inline constexpr double kMaxTargetWeight = 1e3;
inline constexpr double kMaxShapeWeight = 1e6;

// Checks a weight vector against the rig: right length, finite entries within the bounds above, and the shape
// weights they give (Rig::ShapeWeights) within theirs. Throws Error naming the entry or the shape.
void ValidateWeights(const Rig& rig, const std::vector<double>& weights);
// Checks options against the rig they will solve (SolveOptions::Validate, and linear_targets naming its targets):
// throws Error(kInvalidInput) naming the field or the name at fault. Solver's constructor and set_options call it.
void ValidateOptions(const Rig& rig, const SolveOptions& options);
// Checks a whole frame (weights, pins, one transform per collider or none) before anything is solved.
void ValidateFrame(const Rig& rig, const Frame& frame, size_t colliders);

// The linear blendshape: rest + sum_t w_t (target_t - rest) of the mesh vertices, #surface vertices by 3.
Points LinearBlend(const Rig& rig, const std::vector<double>& weights);
// The same for every simulated vertex (#rig vertices by 3).
Points LinearBlendAll(const Rig& rig, const std::vector<double>& weights);

// Blended rest lengths r̄_q = r_q^0 + sum_t w_t (r_q^t - r_q^0), clamped from below (see RigOptions).
void BlendRestLengths(const Rig& rig, const std::vector<double>& weights, std::vector<double>* blended);

class Solver {
 public:
  explicit Solver(std::shared_ptr<const Rig> rig, SolveOptions options = {});
  ~Solver();
  Solver(Solver&&) noexcept;
  Solver& operator=(Solver&&) noexcept;

  // Solves one frame and writes the surface positions (#surface vertices by 3) to *positions. Bad input
  // throws Error; a solve that does not converge returns a summary that says why.
  SolveSummary Solve(const Frame& frame, Points* positions);
  // The same, asking `stop` once per Newton (or L-BFGS) iteration and contact round; when it says true the
  // frame ends at once with Termination::kCancelled (a server stops the work of a cancelled request, or of a
  // slider frame a newer one overtook). `stop` is called on this thread.
  SolveSummary Solve(const Frame& frame, Points* positions, const std::function<bool()>& stop);

  // Where a frame with these weights starts (#rig vertices by 3, before its held vertices are placed).
  Points Start(const std::vector<double>& weights) const;
  // The obstacles of the following frames (paper section 4); each frame may move them.
  void SetColliders(std::vector<Collider> colliders);
  // The last solution including cap and interior vertices (#rig vertices by 3); empty before a solve.
  const Points& all_positions() const;
  // About the most memory this solver holds once it has solved frames (not counting its colliders or the
  // shared rig), for a server's memory budget; known before the first solve: its Cholesky factors (from the
  // size the rig's symbolic analysis gives), the springs' state and the per-vertex buffers. A face of 13k
  // simulated vertices: about 75 MB measured after a Newton frame.
  std::int64_t bytes() const;
  // The same for a solver of this rig with these options, before making one.
  static std::int64_t BytesFor(const Rig& rig, const SolveOptions& options);

  const Rig& rig() const;
  const SolveOptions& options() const;
  void set_options(const SolveOptions& options);

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

// The paper's protocol: weights(alpha) for alpha = i / (steps - 1), i = 0..steps-1 (so the sequence starts
// at the rest shape and ends at `end`). Each frame's weights are alpha * end; each frame is solved alone.
std::vector<Frame> SweepFrames(const std::vector<double>& end, int steps);

}  // namespace springblend
