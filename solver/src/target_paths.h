// Each target's own path, for stateless frames and for the frames that move one target: at rig build, the
// equilibria of the target alone at weight alpha, alpha over [-extension, 1 + extension] (in-betweens blend in
// as the frame's weights would), kept as the physical correction (solved minus linear blend, in the anchor's
// frame) at adaptively chosen samples and interpolated by cubic Hermite splines.
//
// One branch per path, chosen deterministically:
//  - the sweep up from the rest shape (continuation at `intervals` steps per unit, each step started from the
//    polynomial through the branch's last corrections, halved where Newton does not converge);
//  - where it does not end on the target, the sweep down from the target too, for as long as its branch has
//    the lower energy at the steps, and one switch between them: the down branch from the target down to the
//    last such step, the up branch below it (so alpha 0 and 1 are the rest shape and the target exactly, and
//    the choice is per interval);
//  - beyond [0, 1], continuation from the nearer end;
//  - a step that lands far from its extrapolated start went over a fold: the path breaks there.
// Certified, within a cap on samples: every solved step is kept when the cap allows (they were solved anyway,
// and the denser the samples, the closer a frame starts to its answer: on the face, frames in [0, 1] then
// finish locally); else the ends, knots, both sides of switches and folds and a grid of 8 per unit are kept,
// and an interval whose interpolant misses a solved step inside it by
// more than `tolerance` of the diagonal is split at the step nearest its midpoint; an interval with no step
// inside is split until the interpolant at its midpoint is within `tolerance` of an equilibrium solved there
// from it (checks are made against the final samples: an interval next to a new sample is checked again), up
// to a cap on samples.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "anchor.h"
#include "path_field.h"
#include "spring_system.h"
#include "springblend/rig.h"

namespace springblend::internal {

struct TargetPath {
  std::vector<double> alphas;                 // ascending sample weights of the target; 0 and 1 among them
  // Per sample: #vertices by 3, in the anchor's frame, in fixed point (two words where one would put the
  // stored sample out of balance at its own weight).
  std::vector<PathField> corrections;
  // Per sample: the exact derivative of its correction in alpha (#vertices by 3, anchor's frame), from one
  // linear solve with the sample's own Hessian; empty where there is none (an in-between's kink, a sample
  // that is not a minimum, a path loaded from an older cache file): the interpolant then takes a three-point
  // tangent there.
  std::vector<PathField> tangents;
  std::vector<std::uint8_t> breaks;           // per sample: 1 at an in-between's weight (a kink: one-sided tangents)
  // Per interval (alphas.size() - 1): 1 where the check passed, 0 where it did not within the cap, 2 for the
  // interval that switches from the up branch to the down branch, 3 for a fold (the sweep jumped branches).
  std::vector<std::uint8_t> certified;
  double max_error = 0.0;   // largest midpoint error over the certified intervals, of the diagonal
  double build_ms = 0.0;    // wall time of this path's build
  int solves = 0;           // equilibria solved for it (samples and checks)
  int newton_iterations = 0;
  int tangent_cg_iterations = 0;  // conjugate-gradient iterations of the exact tangents' solves
  int checks = 0;           // midpoint checks solved (among the solves)
  int local_checks = 0;     // of them, finished where the interpolant was out of balance only
  int unconverged = 0;      // samples whose solve did not converge (kept as the best found)
  bool empty() const { return corrections.empty(); }
  int samples() const { return static_cast<int>(alphas.size()); }
  int uncertified() const;  // intervals whose check did not pass, and folds (the branch switch not counted)
  // Those intervals' weights, neighbours merged, ascending.
  std::vector<std::pair<double, double>> UncertifiedRanges() const;
  std::int64_t bytes() const;         // memory it holds
  std::int64_t stored_bytes() const;  // its fields' words left in a file (ParseTargetPaths from a file)
};

struct TargetPathsOptions {
  int intervals = 32;          // continuation steps per unit of alpha
  double extension = 0.25;     // beyond [0, 1] on both sides
  double tolerance = 1e-6;     // midpoint error, of the bounding-box diagonal
  int max_samples = 64;        // per target
  const std::function<bool()>* stop = nullptr;  // asked between solves and Newton iterations
  // Where each target's path leaves its fields as soon as it is done (PathField::MoveTo), so a build holds the
  // paths being solved, not those solved; null: they stay in memory.
  std::shared_ptr<PathFile> spool;
  // Called after each target's path is done (from the building thread, serialized by the caller's lock).
  std::function<void(int target, const TargetPath& path)> done;
};

struct TargetPathsReport {
  int samples = 0;      // samples kept, over the targets
  int solves = 0;       // equilibria solved (samples and midpoint checks)
  int unconverged = 0;  // samples whose solve did not converge (kept as the best found)
  int uncertified = 0;  // intervals whose midpoint check did not pass within the cap
  int newton_iterations = 0;
  double max_error = 0.0;
  double ms = 0.0;
  std::string spool_error;  // why a path was held in memory rather than spooled (the first failure); empty
};

// Whether any sculpted shape of the target changes a rest length (else its path is the linear blend).
bool TargetChangesLengths(const Rig& rig, int target);

// Solves every target's path (targets run in parallel). Targets that change no rest length get an empty path.
// Throws Error(kCancelled) when `options.stop` says stop.
std::vector<TargetPath> BuildTargetPaths(const Rig& rig, const TargetPathsOptions& options, TargetPathsReport* report);

// The path's correction at alpha (#vertices by 3, anchor's frame): cubic Hermite between the samples with
// their exact tangents (three-point ones where a sample has none), held at the end samples beyond them.
void EvaluatePath(const TargetPath& path, double alpha, Eigen::MatrixXd* correction);

// A mix frame's start (two or more targets with paths) on the ray base + s (x - base), s in [0, 1], where base
// is the linear blend (with the frame's held coordinates) and x the linear blend plus the targets' corrections.
// Each correction restores what the linear blend loses of its own target's motion alone, so where the targets
// move the same parts their sum overshoots (horse poses: the summed start's energy up to 300 times the
// answer's). From s = 1 down in steps of 1/8 while the energy falls, then one parabolic step between the last
// three; x moves to the lowest energy met. A function of the frame alone; the local minimum nearest s = 1, so a
// sweep's starts move with its weights. Returns s (1: x unchanged; also for frames of fewer than two targets).
bool IsPathMix(const std::vector<TargetPath>& paths, const std::vector<double>& weights);  // ScaleMixStart's frames
double ScaleMixStart(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                     const Eigen::VectorXd& base, const std::function<double(const Eigen::VectorXd&)>& energy,
                     Eigen::VectorXd* x);

// x += sum_t R correction_t(w_t), stacked 3n, over the targets' frame weights, rotated by the frame's anchor
// rotation R.
// `scale`: null, or a factor per target on its correction (0 leaves it out).
void AddPathCorrections(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                        const std::optional<AnchorMotion>& motion, Eigen::VectorXd* x,
                        const std::vector<double>* scale = nullptr);

// Whether a frame with these weights moves one target only, and that target has a path (RefineInPathSpan's
// frames).
bool HasPathSpan(const std::vector<TargetPath>& paths, const std::vector<double>& weights);

// A single-target frame's start x (stacked 3n, held coordinates in place) moved to the lowest energy in the
// span of its path's samples and exact tangents around its weight: one Newton step on their coefficients (the
// reduced Hessian from `springs`, which holds the frame's rest lengths), line-searched on the energy, so the
// energy only ever falls. Nothing is done unless HasPathSpan, or for a start already within
// `residual_tolerance` (largest free force). Returns the span's dimension (0: nothing done).
int RefineInPathSpan(const std::vector<TargetPath>& paths, const std::vector<double>& weights,
                     const std::optional<AnchorMotion>& motion, double residual_tolerance, SpringSystem* springs,
                     const std::vector<char>& held, double diagonal_shift, Eigen::VectorXd* x);

// The paths as bytes (versioned, little-endian) and back. Parse returns nullopt, with the reason in *why, when
// the bytes are not paths of this rig (version, target count, vertex count, sizes).
std::string SerializeTargetPaths(const std::vector<TargetPath>& paths);
// The same bytes told to `write` in consecutive pieces (a few megabytes at most each, read from the paths' file
// where they are stored), so they are never held together; false when `write` returned false.
bool WriteTargetPaths(const std::vector<TargetPath>& paths, const std::function<bool(std::string_view)>& write);
std::optional<std::vector<TargetPath>> ParseTargetPaths(const std::string& bytes, int targets, int vertices,
                                                        std::string* why);
// The same bytes in `file` at [offset, offset + size) (size -1: to its end); the fixed-point fields stay in the
// file (PathField::Stored), read when frames use them.
std::optional<std::vector<TargetPath>> ParseTargetPaths(std::shared_ptr<const PathFile> file, std::int64_t offset,
                                                        std::int64_t size, int targets, int vertices,
                                                        std::string* why);

}  // namespace springblend::internal
