// How several targets combine (SolveOptions::mix, solver/src/mix.h), on the bundled ICT face (jawOpen, mouthClose,
// mouthFunnel, mouthStretch_L, mouthSmile_L) driven by 40 frames of a captured Live Link Face take
// (tests/data/take, MIT): where many expressions act at once the superposed mix stays with what its expressions do
// (within the largest of their own physical corrections of the linear blend), moves with the take (no pops), and every
// frame is a converged, certified local minimum; the paper's blend of rest lengths on the same frames goes farther
// than any of that. A frame that moves one physical target is the paper's in both models, to the bit, and a mix
// goes to it continuously as the other weight goes to 0 (a sweep through the strains' fading out does not pop);
// the default corrective (mouthClose) alone is its linear blend. Each test builds the five-target face rig (30-100 s
// in release).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>

#include "mix.h"
#include "rig_internals.h"
#include "take.h"
#include "target_paths.h"
#include "test_util.h"

namespace springblend {
namespace {

using testing::DataPath;
using testing::MaxDistance;

const std::vector<std::string> kExpressions = {"jawOpen", "mouthClose", "mouthFunnel", "mouthStretch_L",
                                               "mouthSmile_L"};

std::shared_ptr<const Rig> FaceRig() {
  static const std::shared_ptr<const Rig> rig = [] {
    std::vector<TargetSpec> targets;
    for (const auto& name : kExpressions) {
      TargetSpec t;
      t.name = name;
      t.mesh = LoadMesh(DataPath("face/" + name + ".obj"));
      targets.push_back(std::move(t));
    }
    // The mask held at its outer rim, as it is stitched to a head; paths at 8 steps per unit (TestRigOptions).
    RigOptions options = testing::TestRigOptions();
    options.hold_outer_rim = true;
    return Rig::Build(LoadMesh(DataPath("face/generic_neutral_mesh.obj")), std::move(targets), options);
  }();
  return rig;
}

// The take's frames 1140-1179 (every other one: 20 frames at 15 per second) as weights of the rig's targets.
std::vector<std::vector<double>> TakeFrames(const Rig& rig) {
  const cli::Take t = cli::ReadTake(DataPath("take/alex_rom_4_excerpt.csv"));
  const std::vector<std::vector<double>> all = cli::MatchTake(t, rig.target_names()).weights;
  std::vector<std::vector<double>> frames;
  for (size_t i = 0; i < all.size(); i += 2) frames.push_back(all[i]);
  return frames;
}

// The largest vertex move of any physical target's own correction at its weight (its path: the target alone): how
// far the frame may go from its linear blend with nothing added that its expressions lack.
double LargestCorrection(const Rig& rig, const std::vector<double>& weights, const std::vector<char>& linear) {
  double largest = 0.0;
  for (int t = 0; t < rig.num_targets(); ++t) {
    if (weights[t] == 0.0 || linear[t] || rig.internals().paths[t].empty()) continue;
    Eigen::MatrixXd c;
    internal::EvaluatePath(rig.internals().paths[t], weights[t], &c);
    largest = std::max(largest, std::sqrt(c.topRows(rig.num_surface_vertices()).rowwise().squaredNorm().maxCoeff()));
  }
  return largest;
}

TEST(MixTest, ACapturedTakeStaysWithItsExpressionsMovesWithItAndIsCertified) {
  const auto rig = FaceRig();
  const double diagonal = rig->summary().bounding_box_diagonal;
  const std::vector<std::vector<double>> frames = TakeFrames(*rig);
  ASSERT_EQ(frames.size(), 20u);
  SolveOptions options;  // the default: superposed, mouthClose a corrective
  options.certify_minimum = true;
  SolveOptions linear_options;
  linear_options.linear = true;
  Solver solver(rig, options), linear_solver(rig, linear_options);
  const std::vector<char> linear_targets = internal::LinearTargets(*rig, options);
  ASSERT_EQ(std::count(linear_targets.begin(), linear_targets.end(), 1), 1) << "mouthClose is the default corrective";
  std::vector<Points> solved(frames.size()), blended(frames.size());
  int mixes = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    const int moved = static_cast<int>(std::count_if(frames[i].begin(), frames[i].end(), [](double w) { return w != 0.0; }));
    mixes += moved >= 4;
    const SolveSummary s = solver.Solve(Frame{frames[i]}, &solved[i]);
    linear_solver.Solve(Frame{frames[i]}, &blended[i]);
    EXPECT_EQ(s.termination, Termination::kConverged) << "frame " << i << ": " << s.message;
    EXPECT_LE(s.residual, options.residual_tolerance) << "frame " << i;
    EXPECT_EQ(s.minimum, MinimumCheck::kMinimum) << "frame " << i;
    // Nothing its expressions do not do: within the largest of their own corrections (and a dominant target's
    // strains' small give, 0.1 % of the diagonal) of the linear blend.
    const double bound = LargestCorrection(*rig, frames[i], linear_targets) + 1e-3 * diagonal;
    EXPECT_LE(MaxDistance(solved[i], blended[i]), bound) << "frame " << i;
    if (i > 0) {
      // No pop: a step of the answer at most twice the linear blend's where it exceeds 1e-3 of the diagonal.
      const double step = MaxDistance(solved[i], solved[i - 1]);
      const double linear_step = MaxDistance(blended[i], blended[i - 1]);
      if (step > 1e-3 * diagonal) {
        EXPECT_LE(step, 2.0 * linear_step) << "frames " << i - 1 << " to " << i;
      }
    }
  }
  EXPECT_EQ(mixes, static_cast<int>(frames.size())) << "every frame of the excerpt moves four or more expressions";

  // The paper's blend of rest lengths on the take's most mixed frame goes beyond that bound (the mouth inflates):
  // the bound above is one a wrong model fails.
  size_t widest = 0;
  double widest_sum = 0.0;
  for (size_t i = 0; i < frames.size(); ++i) {
    double sum = 0.0;
    for (double w : frames[i]) sum += std::abs(w);
    if (sum > widest_sum) widest_sum = sum, widest = i;
  }
  SolveOptions paper;
  paper.mix = MixModel::kRestLengths;
  Solver paper_solver(rig, paper);
  Points x;
  const SolveSummary s = paper_solver.Solve(Frame{frames[widest]}, &x);
  EXPECT_EQ(s.termination, Termination::kConverged);
  EXPECT_GT(MaxDistance(x, blended[widest]),
            LargestCorrection(*rig, frames[widest], internal::LinearTargets(*rig, options)) + 1e-3 * diagonal);
}

// One rig build for the rest (each test builds the face again in its own process).
TEST(MixTest, OneTargetIsThePapersFrameACorrectiveAloneItsBlendMixesAreStatelessAndBadNamesRefused) {
  const auto rig = FaceRig();
  const double diagonal = rig->summary().bounding_box_diagonal;
  SolveOptions superposed, paper, linear;
  paper.mix = MixModel::kRestLengths;
  linear.linear = true;
  Solver a(rig, superposed), b(rig, paper), l(rig, linear);
  // One physical target: the paper's frame in both models, to the bit.
  for (int t : {0, 2, 4}) {  // jawOpen, mouthFunnel, mouthSmile_L
    for (double w : {0.3, 0.8}) {
      std::vector<double> weights(rig->num_targets(), 0.0);
      weights[t] = w;
      Points x, y;
      ASSERT_TRUE(a.Solve(Frame{weights}, &x).converged());
      ASSERT_TRUE(b.Solve(Frame{weights}, &y).converged());
      EXPECT_EQ(MaxDistance(x, y), 0.0) << rig->target_names()[t] << " at " << w;
    }
  }
  // The default corrective alone is its linear blend; named physical (an empty list) it is the paper's frame again.
  std::vector<double> weights(rig->num_targets(), 0.0);
  weights[1] = 0.4;  // mouthClose
  Points x, y;
  EXPECT_TRUE(a.Solve(Frame{weights}, &x).converged());
  l.Solve(Frame{weights}, &y);
  EXPECT_LE(MaxDistance(x, y), 1e-9 * diagonal);
  SolveOptions none;
  none.linear_targets = std::vector<std::string>{};
  Solver c(rig, none);
  Points z, p;
  ASSERT_TRUE(c.Solve(Frame{weights}, &z).converged());
  ASSERT_TRUE(b.Solve(Frame{weights}, &p).converged());
  EXPECT_EQ(MaxDistance(z, p), 0.0);
  EXPECT_GT(MaxDistance(z, y), 1e-4 * diagonal);
  // As a second target's weight goes to 0 the mix goes to the first target's frame (the paper's) continuously:
  // its strains come back as the first target comes to dominate.
  std::vector<double> one(rig->num_targets(), 0.0);
  one[0] = 0.6;  // jawOpen
  Points single, single_linear;
  ASSERT_TRUE(a.Solve(Frame{one}, &single).converged());
  l.Solve(Frame{one}, &single_linear);
  for (double epsilon : {1e-1, 1e-2, 1e-3, 1e-4}) {
    std::vector<double> two = one;
    two[2] = epsilon;  // mouthFunnel
    Points mixed, mixed_linear;
    const SolveSummary s = a.Solve(Frame{two}, &mixed);
    ASSERT_TRUE(s.converged()) << epsilon;
    l.Solve(Frame{two}, &mixed_linear);
    const double distance = MaxDistance(mixed, single), linear_distance = MaxDistance(mixed_linear, single_linear);
    std::cout << "  mouthFunnel at " << epsilon << ": " << distance / diagonal << " of the diagonal from jawOpen's "
              << "frame (the linear blend " << linear_distance / diagonal << ")\n";
    EXPECT_LE(distance, 2.0 * linear_distance + 1e-6 * diagonal) << epsilon;
  }
  // Along a sweep of mouthFunnel from 0 to 0.6 beside jawOpen at 0.6 the strains fade out as jawOpen stops
  // dominating (the share falls and passes strictly between 0 and 1): every frame converged and certified, no pop.
  {
    SolveOptions certified;
    certified.certify_minimum = true;
    Solver sweep(rig, certified);
    Points previous, previous_linear;
    double previous_share = 1.0;
    int between = 0;
    for (int i = 0; i <= 12; ++i) {
      std::vector<double> two = one;
      two[2] = 0.05 * i;
      Points answer, blend;
      const SolveSummary s = sweep.Solve(Frame{two}, &answer);
      l.Solve(Frame{two}, &blend);
      ASSERT_TRUE(s.converged()) << i << ": " << s.message;
      EXPECT_EQ(s.minimum, MinimumCheck::kMinimum) << i;
      const double share = i == 0 ? 1.0 : s.mix_strain_share;
      EXPECT_LE(share, previous_share + 1e-12) << i;
      between += share > 0.0 && share < 1.0;
      previous_share = share;
      if (i > 0) {
        const double step = MaxDistance(answer, previous), linear_step = MaxDistance(blend, previous_linear);
        if (step > 1e-3 * diagonal) {
          EXPECT_LE(step, 2.0 * linear_step) << "step " << i;
        }
      }
      previous = answer;
      previous_linear = blend;
    }
    EXPECT_GE(between, 1);
  }
  // A mix is the same alone and after other frames.
  const std::vector<std::vector<double>> frames = TakeFrames(*rig);
  Solver sequence(rig), alone(rig);
  Points s, t;
  for (size_t i = 0; i < 4; ++i) sequence.Solve(Frame{frames[i]}, &s);
  alone.Solve(Frame{frames[3]}, &t);
  EXPECT_EQ(MaxDistance(s, t), 0.0);
  // A linear target that is no target of the rig is refused by name, before any frame.
  SolveOptions unknown;
  unknown.linear_targets = std::vector<std::string>{"jawOpen", "mouthCloze"};
  try {
    Solver refused(rig, unknown);
    FAIL() << "an unknown linear target was accepted";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
    EXPECT_NE(std::string(e.what()).find("'mouthCloze'"), std::string::npos) << e.what();
  }
  EXPECT_THROW(a.set_options(unknown), Error);
}

}  // namespace
}  // namespace springblend
