// Baking the physics into a plain blendshape rig: each target's solved path becomes in-betweens (shapes at chosen
// weights, fitted to the whole solved path, played back piecewise linearly, as Maya's in-betweens and Unity's
// multi-frame blend shapes are), and targets whose solved mix differs from the sum of their parts get a combination
// corrective (the solved equilibrium with its drivers at 1, on by the product of their weights, as Maya's
// combinationShape). A linear blendshape evaluator then plays most of the physics with no solver at all.
//
// The bake only asks for solved frames (a FrameSource): the local solver (LocalFrameSource) or a server.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "springblend/mesh.h"
#include "springblend/solve.h"

namespace springblend {

// A solved frame's surface positions (#surface vertices by 3), and whether its solve converged.
struct SolvedShape {
  Points positions;
  bool converged = true;
};
// Solves every weight vector (one weight per target, in the rig's order) and writes one SolvedShape each, in
// order. Throws Error on failure.
using FrameSource = std::function<void(const std::vector<std::vector<double>>& weights, std::vector<SolvedShape>*)>;

// Solves frames with the local solver, in parallel (one Solver per worker thread: frames are stateless, so the
// answers do not depend on the threads).
FrameSource LocalFrameSource(std::shared_ptr<const Rig> rig, SolveOptions options = {});

enum class BakePairs {
  kAuto,  // every pair of targets that move a common region, kept where the solved mix misses by pair_threshold
  kNone,  // no pair correctives (the input rig's own combinations are still baked)
  kList,  // the pairs in BakeOptions::pairs, kept whatever their error
};

struct BakeOptions {
  // In-betweens per target: exactly this many, or with tolerance > 0 the fewest (up to this many) that bring
  // the largest error along the path within tolerance. Range [0, samples - 1].
  int inbetweens = 3;
  double tolerance = 0.0;  // of the rest shape's bounding-box diagonal; 0: use `inbetweens`
  // Each target's path is solved at samples + 1 evenly spaced weights in [0, 1], and where it snaps between two
  // of them (a step far longer than the steps beside it), at weights bisecting that gap down to 1/64 of a sample;
  // the in-betweens' weights are chosen among them. Range [2, 1024].
  int samples = 32;
  // false: each in-between's shape is fitted to the whole path (per vertex, the smallest largest distance from
  // the solved samples: a straight segment is best off the curve it cuts, about halving the error); true: the
  // in-betweens are the solved frames at their weights (the baked rig then reproduces them exactly). Either
  // way the full shape is the solved frame at 1 and the rest shape is the rig's.
  bool solved_inbetweens = false;
  BakePairs pair_mode = BakePairs::kAuto;
  std::vector<std::pair<std::string, std::string>> pairs;  // kList: target names
  // kAuto: a pair gets a corrective when its solved mix (both at 1) is farther than this (of the diagonal)
  // from what the baked rig gives there without it, and the corrective lowers the baked rig's error summed over
  // the pair's frames at (1, 1), (1/2, 1/2), (1, 1/2) and (1/2, 1). Range (0, 1).
  double pair_threshold = 1e-3;
  // kAuto: two targets move a common region when some vertex moves by more than region_fraction of each
  // target's largest move in both. Range (0, 1).
  double region_fraction = 0.01;
  // Called with what is done ("paths" after each target, then "combinations"), on the calling thread.
  std::function<void(const std::string& stage, int done, int total)> progress;
  void Validate() const;  // throws Error(kInvalidInput) naming the field
};

// What the bake starts from: the rig's rest surface, its weight order and its own combinations.
struct BakeInput {
  Points rest;  // #surface vertices by 3
  std::vector<std::string> target_names;
  struct Combination {
    std::string name;
    std::vector<int> drivers;  // indices into target_names
  };
  std::vector<Combination> combinations;
  double diagonal = 0.0;  // the rest shape's bounding-box diagonal (errors are reported as fractions of it)
};
// The input of a local rig.
BakeInput BakeInputOf(const Rig& rig);

struct BakedShape {
  double weight = 0.0;
  Points positions;
};
struct BakedTarget {
  std::string name;
  std::vector<BakedShape> inbetweens;  // ascending weights in (0, 1)
  Points full;                         // the solved shape at weight 1
  int snaps = 0;              // places where the path snaps between samples (a fold), located by bisection
  double max_error = 0.0;     // largest distance of a vertex, baked against solved, over the path's samples
  double linear_error = 0.0;  // the same for the straight blend from the rest shape to `full`
  // A lower bound of max_error for any rig that plays this target piecewise linearly with as many in-betweens,
  // wherever they are and whatever their shapes: the format's own floor on this path (bake.cc says why).
  double floor = 0.0;
};
struct BakedCombination {
  std::string name;
  std::vector<int> drivers;
  Points shape;  // the sculpt with every driver at 1 (a rig file's combination mesh)
  double error_without = 0.0;  // the baked rig's distance from the solved mix there without this corrective
  bool from_rig = false;       // one of the input rig's combinations (else a pair the bake found)
};
struct BakeSummary {
  int frames = 0;  // frames solved
  int unconverged_frames = 0;
  int candidate_pairs = 0;  // kAuto: pairs that move a common region (their mixes were solved)
  int kept_pairs = 0;
  int refused_pairs = 0;  // kAuto: beyond the threshold at (1, 1), but the corrective did not pay inside the range
  int snaps = 0;          // over the targets' paths: snaps located between samples
  double max_error = 0.0;  // over every target's path samples, of the diagonal
  double linear_max_error = 0.0;
  double floor = 0.0;  // the largest of the targets' floors
  // kAuto: a lower bound of the largest error, over a candidate pair's frames at weights {0, 1/2, 1}^2, of any rig
  // that plays each target alone however it likes (any in-betweens) plus a corrective on by the product of the
  // weights; the largest over the candidate pairs (bake.cc says why). 0 without candidates.
  double pair_floor = 0.0;
  bool solved_inbetweens = false;  // BakeOptions::solved_inbetweens
  double inbetweens_ms = 0.0;  // choosing (and fitting) the in-betweens, part of ms
  double ms = 0.0;
};
struct BakedRig {
  Points rest;
  std::vector<BakedTarget> targets;
  std::vector<BakedCombination> combinations;
  double diagonal = 0.0;
  BakeSummary summary;

  // The plain linear blendshape of the baked rig (rig-file semantics: in-betweens piecewise linearly, a
  // combination by the product of its drivers' weights, less that product on each driver's full shape).
  Points Evaluate(const std::vector<double>& weights) const;
};

BakedRig BakeRig(const BakeInput& input, const FrameSource& frames, const BakeOptions& options = {});

}  // namespace springblend
