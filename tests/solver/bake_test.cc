// Baking a rig into a plain blendshape rig (springblend/bake.h), on the bundled cylinder with an in-between and a
// combination: the bake reproduces the solved frames it keeps exactly (full shapes, the combination with its
// drivers at 1, and with solved_inbetweens its in-betweens), fitted in-betweens come closer to the path than the
// solved frames would, the bake beats the plain linear blendshape at weights it never saw, its evaluator is the
// rig-file semantics (a Rig built from the baked shapes blends the same), and more in-betweens never do worse.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "springblend/bake.h"
#include "springblend/error.h"
#include "springblend/rig.h"
#include "springblend/solve.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CatchError;
using testing::DataPath;
using testing::MaxDistance;

// The cylinder bending (with an in-between at 0.5 that is another pose) and twisting, and their corrective.
std::shared_ptr<const Rig> Cylinder() {
  std::vector<TargetSpec> specs(3);
  specs[0].name = "bend";
  specs[0].mesh = LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"));
  specs[0].inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj"))});
  specs[1].name = "twist";
  specs[1].mesh = LoadMesh(DataPath("cylinder/poses-2_cylinder-3.obj"));
  specs[2].name = "bend_twist";
  specs[2].mesh = LoadMesh(DataPath("cylinder/poses-2_cylinder-4.obj"));
  specs[2].combination = {"bend", "twist"};
  return Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), std::move(specs), testing::TestRigOptions());
}

Points Solved(const std::shared_ptr<const Rig>& rig, const std::vector<double>& weights) {
  Solver solver(rig);
  Points x;
  const SolveSummary summary = solver.Solve({weights}, &x);
  EXPECT_TRUE(summary.converged()) << summary.message;
  return x;
}

class BakeTest : public ::testing::Test {
 protected:
  static std::shared_ptr<const Rig> rig() {
    static const std::shared_ptr<const Rig> rig = Cylinder();
    return rig;
  }
  static BakeOptions Options(bool solved_inbetweens) {
    BakeOptions options;
    options.samples = 16;
    options.inbetweens = 3;
    options.solved_inbetweens = solved_inbetweens;
    return options;
  }
  static const BakedRig& baked() {  // in-betweens fitted to the path (the default)
    static const BakedRig baked = BakeRig(BakeInputOf(*rig()), LocalFrameSource(rig()), Options(false));
    return baked;
  }
  static const BakedRig& on_path() {  // the solved frames as in-betweens
    static const BakedRig baked = BakeRig(BakeInputOf(*rig()), LocalFrameSource(rig()), Options(true));
    return baked;
  }
};

TEST_F(BakeTest, ReproducesTheSolvedFramesItKeeps) {
  for (const BakedRig* b : {&baked(), &on_path()}) {
    const double diagonal = rig()->summary().bounding_box_diagonal;
    ASSERT_EQ(b->targets.size(), 2u);
    EXPECT_EQ(b->summary.unconverged_frames, 0);
    for (size_t t = 0; t < b->targets.size(); ++t) {
      std::vector<double> one(2, 0.0);
      one[t] = 1.0;
      EXPECT_LE(MaxDistance(b->Evaluate(one), Solved(rig(), one)), 1e-9 * diagonal) << b->targets[t].name;
    }
    // The rig's own combination is baked, with the mix it corrects solved.
    ASSERT_GE(b->combinations.size(), 1u);
    EXPECT_TRUE(b->combinations[0].from_rig);
    EXPECT_LE(MaxDistance(b->Evaluate({1.0, 1.0}), Solved(rig(), {1.0, 1.0})), 1e-9 * diagonal);
    EXPECT_LE(MaxDistance(b->Evaluate({0.0, 0.0}), rig()->rest().vertices), 0.0);
  }
}

TEST_F(BakeTest, SolvedInbetweensAreTheSolvedFrames) {
  const BakedRig& b = on_path();
  const double diagonal = rig()->summary().bounding_box_diagonal;
  EXPECT_EQ(b.combinations[0].drivers, (std::vector<int>{0, 1}));
  for (size_t t = 0; t < b.targets.size(); ++t) {
    const BakedTarget& target = b.targets[t];
    EXPECT_EQ(target.inbetweens.size(), 3u) << target.name;
    for (const BakedShape& s : target.inbetweens) {
      std::vector<double> w(2, 0.0);
      w[t] = s.weight;
      EXPECT_GT(s.weight, 0.0);
      EXPECT_LT(s.weight, 1.0);
      EXPECT_LE(MaxDistance(b.Evaluate(w), Solved(rig(), w)), 1e-9 * diagonal) << target.name << " at " << s.weight;
    }
  }
}

TEST_F(BakeTest, FittedInbetweensComeCloserToThePathThanTheSolvedFrames) {
  // A straight segment is best off the curve it cuts: fitted in-betweens are no farther from the samples than the
  // solved frames at the search's weights (by construction), and where that gains a margin (on the bend, whose
  // path is smooth at this resolution; the twist's gains little), the gain holds at 32 weights between the
  // samples that neither bake saw.
  const double diagonal = rig()->summary().bounding_box_diagonal;
  int compared = 0;
  for (size_t t = 0; t < 2; ++t) {
    const BakedTarget& fitted = baked().targets[t];
    const BakedTarget& solved = on_path().targets[t];
    EXPECT_LE(fitted.max_error, solved.max_error) << fitted.name;
    ASSERT_EQ(fitted.inbetweens.size(), 3u);
    if (fitted.max_error > 0.8 * solved.max_error) continue;
    ++compared;
    double fitted_largest = 0.0, solved_largest = 0.0;
    for (int j = 0; j < 32; ++j) {
      std::vector<double> w(2, 0.0);
      w[t] = (j + 0.5) / 32;
      const Points x = Solved(rig(), w);
      fitted_largest = std::max(fitted_largest, MaxDistance(baked().Evaluate(w), x) / diagonal);
      solved_largest = std::max(solved_largest, MaxDistance(on_path().Evaluate(w), x) / diagonal);
    }
    EXPECT_LT(fitted_largest, 0.8 * solved_largest) << fitted.name;
  }
  EXPECT_GE(compared, 1);
  EXPECT_FALSE(baked().summary.solved_inbetweens);
  EXPECT_TRUE(on_path().summary.solved_inbetweens);
}

TEST_F(BakeTest, BeatsTheLinearBlendAtWeightsItNeverSaw) {
  const BakedRig& b = baked();
  const double diagonal = rig()->summary().bounding_box_diagonal;
  // Off the 1/16 grid, inside [0, 1].
  for (double alpha : {0.09, 0.23, 0.41, 0.58, 0.77, 0.95}) {
    for (int t = 0; t < 2; ++t) {
      std::vector<double> w(2, 0.0);
      w[t] = alpha;
      const Points solved = Solved(rig(), w);
      const double baked_error = MaxDistance(b.Evaluate(w), solved) / diagonal;
      const double linear_error = MaxDistance(LinearBlend(*rig(), w), solved) / diagonal;
      EXPECT_LT(baked_error, linear_error) << b.targets[t].name << " at " << alpha;
      // Within a few times what the bake measured on its own samples.
      EXPECT_LE(baked_error, 4.0 * b.targets[t].max_error + 1e-6) << b.targets[t].name << " at " << alpha;
    }
  }
  // A mix: the corrective carries the interaction of the paper's blend of rest lengths, the model for a pose rig
  // whose targets rotate the same parts (under the default superposed mix the drivers' corrections are capped where
  // they overlap and fade as the sculpted combination takes over: sub-additive, which a blendshape rig is not).
  const std::vector<double> mix = {0.7, 0.6};
  SolveOptions paper;
  paper.mix = MixModel::kRestLengths;
  Solver solver(rig(), paper);
  Points solved;
  ASSERT_TRUE(solver.Solve({mix}, &solved).converged());
  EXPECT_LT(MaxDistance(b.Evaluate(mix), solved), MaxDistance(LinearBlend(*rig(), mix), solved));
}

TEST_F(BakeTest, ItsEvaluatorIsTheRigFileSemantics) {
  // A rig built from the baked shapes (as `blend --rig OUT/rig.json --linear` builds it) blends as Evaluate does.
  const BakedRig& b = baked();
  const TriangleMesh& rest = rig()->rest();
  std::vector<TargetSpec> specs;
  const auto mesh = [&](const std::string& name, const Points& p) {
    TriangleMesh m;
    m.name = name;
    m.vertices = p;
    m.faces = rest.faces;
    return m;
  };
  for (const BakedTarget& t : b.targets) {
    TargetSpec spec;
    spec.name = t.name;
    spec.mesh = mesh(t.name, t.full);
    for (const BakedShape& s : t.inbetweens) spec.inbetweens.push_back({s.weight, mesh(t.name, s.positions)});
    specs.push_back(std::move(spec));
  }
  for (const BakedCombination& c : b.combinations) {
    TargetSpec spec;
    spec.name = c.name + "_baked";
    spec.mesh = mesh(spec.name, c.shape);
    for (int d : c.drivers) spec.combination.push_back(b.targets[d].name);
    specs.push_back(std::move(spec));
  }
  RigOptions options;
  options.target_paths = false;
  options.interior = false;
  options.shell = false;
  options.anchor = false;
  const auto plain = Rig::Build(rest, std::move(specs), options);
  const double diagonal = rig()->summary().bounding_box_diagonal;
  for (const std::vector<double>& w : std::vector<std::vector<double>>{
           {0.3, 0.0}, {0.0, 0.8}, {0.45, 0.7}, {1.0, 1.0}, {1.2, -0.1}, {-0.2, 0.5}}) {
    EXPECT_LE(MaxDistance(LinearBlend(*plain, w), b.Evaluate(w)), 1e-12 * diagonal) << w[0] << ", " << w[1];
  }
}

TEST_F(BakeTest, MoreInbetweensNeverDoWorseAndATolerancePicksTheFewest) {
  const BakeInput input = BakeInputOf(*rig());
  const FrameSource frames = LocalFrameSource(rig());
  double last = std::numeric_limits<double>::infinity();
  for (int k : {0, 1, 3}) {
    BakeOptions options;
    options.samples = 8;
    options.inbetweens = k;
    options.pair_mode = BakePairs::kNone;
    const BakedRig b = BakeRig(input, frames, options);
    EXPECT_LE(b.summary.max_error, last) << k << " in-betweens";
    last = b.summary.max_error;
    // No in-between: the straight blend from the rest shape to the solved target.
    if (k == 0) {
      EXPECT_DOUBLE_EQ(b.summary.max_error, b.summary.linear_max_error);
    }
  }
  BakeOptions loose;
  loose.samples = 8;
  loose.inbetweens = 7;
  loose.tolerance = 0.5;  // half the diagonal: any path is within it
  loose.pair_mode = BakePairs::kNone;
  for (const BakedTarget& t : BakeRig(input, frames, loose).targets) EXPECT_TRUE(t.inbetweens.empty()) << t.name;
}

// BakedTarget::floor is a lower bound for any piecewise-linear rig with as many in-betweens: the bake's own fitted
// and solved in-betweens never beat it, it falls (or stays) with more in-betweens, and with none it is half the
// straight blend's error (the one straight piece from the rest shape to the target can at best halve it).
TEST_F(BakeTest, TheFloorBoundsEveryBakeWithAsManyInbetweens) {
  const BakeInput input = BakeInputOf(*rig());
  const FrameSource frames = LocalFrameSource(rig());
  std::vector<double> last(input.target_names.size(), std::numeric_limits<double>::infinity());
  for (int k : {0, 1, 3}) {
    for (const bool solved : {false, true}) {
      BakeOptions options;
      options.samples = 8;
      options.inbetweens = k;
      options.solved_inbetweens = solved;
      options.pair_mode = BakePairs::kNone;
      const BakedRig b = BakeRig(input, frames, options);
      double largest = 0.0;
      for (size_t t = 0; t < b.targets.size(); ++t) {
        const BakedTarget& target = b.targets[t];
        SCOPED_TRACE(target.name + ", " + std::to_string(k) + " in-betweens" + (solved ? ", solved" : ", fitted"));
        EXPECT_GT(target.floor, 0.0);  // both targets bend or twist: no straight piece follows them
        EXPECT_LE(target.floor, target.max_error * (1.0 + 1e-12));
        EXPECT_LE(target.floor, last[t] * (1.0 + 1e-12));
        if (k == 0) {
          EXPECT_NEAR(target.floor, 0.5 * target.linear_error, 1e-15);
        }
        largest = std::max(largest, target.floor);
        if (solved) last[t] = target.floor;
      }
      EXPECT_EQ(b.summary.floor, largest);
    }
  }
}

TEST_F(BakeTest, APairFoundByTheSearchIsKeptOnlyWhereItPaysAndThenReproducesItsMix) {
  // The same cylinder without its combination: bend and twist move a common region, so their pair is a candidate.
  std::vector<TriangleMesh> targets = {LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj")),
                                       LoadMesh(DataPath("cylinder/poses-2_cylinder-3.obj"))};
  const auto plain = Rig::Build(LoadMesh(DataPath("cylinder/cylinder.obj")), std::move(targets),
                                testing::TestRigOptions());
  BakeOptions options;
  options.samples = 8;
  options.inbetweens = 2;
  // The frames of the paper's blend of rest lengths, where the bent and twisted cylinder at (1, 1) is a physical
  // answer of its own. (The default superposed mix adds the sculpts' deltas there, as a blendshape rig does, each
  // target's correction vanishing at its own sculpt: at the corners nothing is left for a pair to correct.)
  SolveOptions paper;
  paper.mix = MixModel::kRestLengths;
  const auto Solved = [&](const std::shared_ptr<const Rig>& rig, const std::vector<double>& weights) {
    Solver solver(rig, paper);
    Points x;
    EXPECT_TRUE(solver.Solve({weights}, &x).converged());
    return x;
  };
  const auto LocalFrameSource = [&](std::shared_ptr<const Rig> rig) { return springblend::LocalFrameSource(rig, paper); };
  const BakedRig b = BakeRig(BakeInputOf(*plain), LocalFrameSource(plain), options);
  EXPECT_EQ(b.summary.candidate_pairs, 1);
  EXPECT_EQ(b.summary.kept_pairs + b.summary.refused_pairs, 1);
  const double diagonal = plain->summary().bounding_box_diagonal;
  const Points mix = Solved(plain, {1.0, 1.0});
  const Points half = Solved(plain, {0.5, 0.5});
  BakeOptions none = options;
  none.pair_mode = BakePairs::kNone;
  const BakedRig without = BakeRig(BakeInputOf(*plain), LocalFrameSource(plain), none);
  if (b.summary.kept_pairs == 1) {
    ASSERT_EQ(b.combinations.size(), 1u);
    EXPECT_FALSE(b.combinations[0].from_rig);
    EXPECT_GT(b.combinations[0].error_without, options.pair_threshold);
    EXPECT_LE(MaxDistance(b.Evaluate({1.0, 1.0}), mix), 1e-9 * diagonal);
  } else {
    EXPECT_TRUE(b.combinations.empty());
  }
  // Kept or not, the baked rig is no worse than without the search where the rule looked.
  EXPECT_LE(MaxDistance(b.Evaluate({1.0, 1.0}), mix) + MaxDistance(b.Evaluate({0.5, 0.5}), half),
            MaxDistance(without.Evaluate({1.0, 1.0}), mix) + MaxDistance(without.Evaluate({0.5, 0.5}), half) +
                1e-12 * diagonal);
  // Listed pairs are kept whatever their error.
  BakeOptions listed = options;
  listed.pair_mode = BakePairs::kList;
  listed.pairs = {{plain->target_names()[1], plain->target_names()[0]}};
  const BakedRig l = BakeRig(BakeInputOf(*plain), LocalFrameSource(plain), listed);
  ASSERT_EQ(l.combinations.size(), 1u);
  EXPECT_EQ(l.combinations[0].drivers, (std::vector<int>{0, 1}));
  EXPECT_LE(MaxDistance(l.Evaluate({1.0, 1.0}), mix), 1e-9 * diagonal);
  // The pairs' floor bounds every one of these rigs over the pair's frames at {0, 1/2, 1}^2 (in-betweens and a
  // corrective on by the product of the weights, or none), and is not trivially 0: bend and twist interact.
  EXPECT_GT(b.summary.pair_floor, 0.0);
  EXPECT_EQ(without.summary.pair_floor, 0.0);  // no candidates, no floor
  for (const BakedRig* rig : {&b, &without, &l}) {
    double largest = 0.0;
    for (const double wa : {0.0, 0.5, 1.0}) {
      for (const double wb : {0.0, 0.5, 1.0}) {
        largest = std::max(largest, MaxDistance(rig->Evaluate({wa, wb}), Solved(plain, {wa, wb})) / diagonal);
      }
    }
    EXPECT_LE(b.summary.pair_floor, largest * (1.0 + 1e-12));
  }
}

// A path that snaps between two samples (a fold: here a made-up one, at weight 0.3712, on a path that is linear
// on either side): the bake locates the snap by bisection and jumps where the path does, so frames beside the
// snap are reproduced (a straight path either side) rather than blended across it; a steep but smooth path is not
// taken for a snap.
TEST(BakeSnaps, ASnapBetweenSamplesIsLocatedAndTheBakeJumpsThere) {
  constexpr double kSnap = 0.3712;
  BakeInput input;
  input.rest = Points::Zero(4, 3);
  input.rest.col(0) << 0.0, 1.0, 0.0, 1.0;
  input.rest.col(1) << 0.0, 0.0, 1.0, 1.0;
  input.target_names = {"fold", "smooth"};
  input.diagonal = std::sqrt(2.0);
  const auto shape = [&](const std::vector<double>& w) {
    Points x = input.rest;
    x.col(2).array() += 0.5 * w[0] + (w[0] > kSnap ? 0.2 : 0.0);  // the fold: a jump of 0.2
    x.col(0).array() += 0.3 * (std::tanh(12.0 * (w[1] - 0.5)) - std::tanh(-6.0));  // steep in the middle, smooth
    return x;
  };
  const FrameSource frames = [&](const std::vector<std::vector<double>>& weights, std::vector<SolvedShape>* out) {
    out->clear();
    for (const auto& w : weights) out->push_back({shape(w), true});
  };
  BakeOptions options;
  options.samples = 16;
  options.inbetweens = 3;
  options.pair_mode = BakePairs::kNone;
  for (bool solved : {false, true}) {
    options.solved_inbetweens = solved;
    const BakedRig b = BakeRig(input, frames, options);
    EXPECT_EQ(b.targets[0].snaps, 1) << solved;
    EXPECT_EQ(b.targets[1].snaps, 0) << solved;
    EXPECT_EQ(b.summary.snaps, 1) << solved;
    // Two in-betweens bracket the snap within 1/64 of a sample.
    const auto& in = b.targets[0].inbetweens;
    bool bracketed = false;
    for (size_t k = 0; k + 1 < in.size(); ++k) {
      bracketed |= in[k].weight <= kSnap && in[k + 1].weight > kSnap && in[k + 1].weight - in[k].weight <= 1.0 / (16 * 64) + 1e-12;
    }
    EXPECT_TRUE(bracketed) << solved;
    for (double alpha : {0.1, 0.3, 0.36, 0.38, 0.45, 0.8}) {
      EXPECT_LE(MaxDistance(b.Evaluate({alpha, 0.0}), shape({alpha, 0.0})), 1e-9) << alpha << " " << solved;
    }
  }
}

TEST_F(BakeTest, BadOptionsAndPairsAreRefusedByName) {
  const BakeInput input = BakeInputOf(*rig());
  const FrameSource frames = LocalFrameSource(rig());
  BakeOptions options;
  options.samples = 4;
  options.inbetweens = 4;
  EXPECT_THAT(CatchError([&] { BakeRig(input, frames, options); }).what(), HasSubstr("inbetweens = 4"));
  options.inbetweens = 1;
  options.pair_mode = BakePairs::kList;
  options.pairs = {{"bend", "twirl"}};
  const Error e = CatchError([&] { BakeRig(input, frames, options); });
  EXPECT_EQ(e.code(), ErrorCode::kNotFound);
  EXPECT_THAT(e.what(), HasSubstr("'twirl'"));
  EXPECT_THAT(e.what(), HasSubstr("targets: bend, twist"));
}

}  // namespace
}  // namespace springblend
