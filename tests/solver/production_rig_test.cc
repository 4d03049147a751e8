// Production rigs (TargetSpec): in-betweens reproduced at their weights, combinations with their drivers at 1,
// masks (all zero = the rest shape, all one = no mask), the shape weights they blend with, and each bad spec
// refused with a message naming the target and the field. On the bundled cylinder and face.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "springblend/rig.h"
#include "springblend/solve.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::AllOf;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using testing::CatchError;
using testing::DataPath;
using testing::MaxDistance;

constexpr double kShapeTolerance = 1e-6;  // of the bounding-box diagonal

TargetSpec Spec(const std::string& name, const std::string& mesh) {
  TargetSpec spec;
  spec.name = name;
  spec.mesh = LoadMesh(DataPath(mesh));
  return spec;
}

TriangleMesh Rest(const std::string& mesh) { return LoadMesh(DataPath(mesh)); }

// Solves one frame and expects it converged; returns the surface.
Points SolveFrame(const std::shared_ptr<const Rig>& rig, const std::vector<double>& weights) {
  Solver solver(rig);
  Points x;
  const SolveSummary summary = solver.Solve({weights}, &x);
  EXPECT_TRUE(summary.converged()) << summary.message;
  return x;
}

double Diagonal(const Rig& rig) { return rig.summary().bounding_box_diagonal; }

// A bent cylinder (one end still) with an in-between: the 0.5 shape is another pose, not the half-way blend.
std::shared_ptr<const Rig> CylinderWithInbetween(RigOptions options = {}) {
  TargetSpec bend = Spec("bend", "cylinder/poses-2_cylinder-4.obj");
  bend.inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
  std::vector<TargetSpec> specs;
  specs.push_back(std::move(bend));
  return Rig::Build(Rest("cylinder/cylinder.obj"), std::move(specs), options);
}

TEST(ProductionRig, InbetweenIsReproducedAtItsWeight) {
  const auto rig = CylinderWithInbetween();
  ASSERT_EQ(rig->num_targets(), 1);
  ASSERT_EQ(rig->num_shapes(), 2);
  const double tolerance = kShapeTolerance * Diagonal(*rig);
  const Points half = LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj")).vertices;
  const Points full = LoadMesh(DataPath("cylinder/poses-2_cylinder-4.obj")).vertices;
  EXPECT_LE(MaxDistance(SolveFrame(rig, {0.5}), half), tolerance);
  EXPECT_LE(MaxDistance(SolveFrame(rig, {1.0}), full), tolerance);
  EXPECT_LE(MaxDistance(SolveFrame(rig, {0.0}), rig->rest().vertices), tolerance);
  // Between the knots the linear blendshape runs piecewise linearly through the in-between.
  const Points& rest = rig->rest().vertices;
  EXPECT_LE(MaxDistance(LinearBlend(*rig, {0.25}), rest + 0.5 * (half - rest)), 1e-12 * Diagonal(*rig));
  EXPECT_LE(MaxDistance(LinearBlend(*rig, {0.75}), 0.5 * (half + full)), 1e-12 * Diagonal(*rig));
  // And a frame between them is a converged equilibrium of its own.
  SolveFrame(rig, {0.75});
}

TEST(ProductionRig, ShapeWeightsAreHatFunctionsExtrapolatedAtTheEnds) {
  const auto rig = CylinderWithInbetween(testing::NoPathsRigOptions());
  // Shapes: 0 = bend at 1, 1 = the in-between at 0.5.
  EXPECT_THAT(rig->ShapeWeights({0.0}), ElementsAre(0.0, 0.0));
  EXPECT_THAT(rig->ShapeWeights({0.25}), ElementsAre(0.0, 0.5));
  EXPECT_THAT(rig->ShapeWeights({0.5}), ElementsAre(0.0, 1.0));
  EXPECT_THAT(rig->ShapeWeights({0.75}), ElementsAre(0.5, 0.5));
  EXPECT_THAT(rig->ShapeWeights({1.0}), ElementsAre(1.0, 0.0));
  EXPECT_THAT(rig->ShapeWeights({1.5}), ElementsAre(2.0, -1.0));
  EXPECT_THAT(rig->ShapeWeights({-0.5}), ElementsAre(0.0, -1.0));
}

// Two targets and their corrective: the sculpt with both on is a third pose.
std::vector<TargetSpec> CylinderCombination() {
  std::vector<TargetSpec> specs;
  specs.push_back(Spec("a", "cylinder/poses-2_cylinder-1.obj"));
  specs.push_back(Spec("b", "cylinder/poses-2_cylinder-3.obj"));
  TargetSpec both = Spec("a_b", "cylinder/poses-2_cylinder-4.obj");
  both.combination = {"a", "b"};
  specs.push_back(std::move(both));
  return specs;
}

TEST(ProductionRig, CombinationIsReproducedWithItsDriversAtOne) {
  const auto rig = Rig::Build(Rest("cylinder/cylinder.obj"), CylinderCombination());
  ASSERT_EQ(rig->num_targets(), 2);
  EXPECT_THAT(rig->target_names(), ElementsAre("a", "b"));
  EXPECT_THAT(rig->combination_names(), ElementsAre("a_b"));
  const double tolerance = kShapeTolerance * Diagonal(*rig);
  EXPECT_LE(MaxDistance(SolveFrame(rig, {1.0, 1.0}), LoadMesh(DataPath("cylinder/poses-2_cylinder-4.obj")).vertices),
            tolerance);
  // Each driver alone is its own target: the corrective is off.
  EXPECT_LE(MaxDistance(SolveFrame(rig, {1.0, 0.0}), LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj")).vertices),
            tolerance);
  EXPECT_LE(MaxDistance(SolveFrame(rig, {0.0, 1.0}), LoadMesh(DataPath("cylinder/poses-2_cylinder-3.obj")).vertices),
            tolerance);
  // On by the product of its drivers' weights, less that on each driver's shape.
  EXPECT_THAT(rig->ShapeWeights({0.5, 0.4}), ElementsAre(0.5 - 0.2, 0.4 - 0.2, 0.2));
  SolveFrame(rig, {0.5, 0.4});
}

TEST(ProductionRig, AllZeroMaskTurnsTheTargetOffAndAllOneChangesNothing) {
  std::vector<TargetSpec> zero;
  zero.push_back(Spec("bend", "cylinder/poses-1_cylinder-4.obj"));
  zero[0].mask.assign(420, 0.0);
  const auto off = Rig::Build(Rest("cylinder/cylinder.obj"), std::move(zero), testing::NoPathsRigOptions());
  EXPECT_LE(MaxDistance(SolveFrame(off, {1.0}), off->rest().vertices), kShapeTolerance * Diagonal(*off));

  std::vector<TargetSpec> one;
  one.push_back(Spec("bend", "cylinder/poses-1_cylinder-4.obj"));
  one[0].mask.assign(420, 1.0);
  const auto masked = Rig::Build(Rest("cylinder/cylinder.obj"), std::move(one), testing::NoPathsRigOptions());
  std::vector<TargetSpec> plain;
  plain.push_back(Spec("bend", "cylinder/poses-1_cylinder-4.obj"));
  const auto unmasked = Rig::Build(Rest("cylinder/cylinder.obj"), std::move(plain), testing::NoPathsRigOptions());
  for (double w : {0.5, 1.0}) {
    EXPECT_LE(MaxDistance(SolveFrame(masked, {w}), SolveFrame(unmasked, {w})), kShapeTolerance * Diagonal(*masked))
        << "weight " << w;
  }
}

TEST(ProductionRig, PartialMaskScalesOffsetsAndRestLengthChanges) {
  std::vector<TargetSpec> specs;
  specs.push_back(Spec("bend", "cylinder/poses-1_cylinder-4.obj"));
  std::vector<double> mask(420);
  for (size_t v = 0; v < mask.size(); ++v) mask[v] = v % 3 == 0 ? 1.0 : (v % 3 == 1 ? 0.5 : 0.0);
  specs[0].mask = mask;
  const auto rig = Rig::Build(Rest("cylinder/cylinder.obj"), std::move(specs), testing::NoPathsRigOptions());
  std::vector<TargetSpec> plain;
  plain.push_back(Spec("bend", "cylinder/poses-1_cylinder-4.obj"));
  const auto unmasked = Rig::Build(Rest("cylinder/cylinder.obj"), std::move(plain), testing::NoPathsRigOptions());
  const Points& rest = rig->rest().vertices;
  const Points& full = unmasked->target(0).vertices;
  for (int v = 0; v < 420; ++v) {
    EXPECT_LE((rig->target(0).vertices.row(v) - (rest.row(v) + mask[v] * (full.row(v) - rest.row(v)))).norm(), 1e-12)
        << "vertex " << v;
  }
  // Surface springs: the change of rest length scaled by the mean of the two ends' mask values.
  for (int q = 0; q < rig->num_springs(); ++q) {
    const int a = rig->spring_a()[q], b = rig->spring_b()[q];
    if (a >= 420 || b >= 420) continue;
    EXPECT_NEAR(rig->rest_length_delta(0)[q], 0.5 * (mask[a] + mask[b]) * unmasked->rest_length_delta(0)[q], 1e-12)
        << "spring " << q;
  }
  SolveFrame(rig, {1.0});
}

// The face mask (open, a shell): an all-zero mask is the rest shape, an all-one mask no mask, and an
// in-between sculpted off the line (70% of the jaw at weight 0.5) is reproduced at 0.5.
TEST(ProductionRig, FaceMasksAndInbetween) {
  RigOptions options;
  options.target_paths = false;  // exactness does not need them; keeps the test short
  const TriangleMesh jaw = LoadMesh(DataPath("face/jawOpen.obj"));
  const TriangleMesh rest = Rest("face/generic_neutral_mesh.obj");
  const int n = static_cast<int>(rest.vertices.rows());

  std::vector<TargetSpec> zero(1);
  zero[0].name = "jawOpen";
  zero[0].mesh = jaw;
  zero[0].mask.assign(n, 0.0);
  const auto off = Rig::Build(rest, std::move(zero), options);
  EXPECT_LE(MaxDistance(SolveFrame(off, {1.0}), rest.vertices), kShapeTolerance * Diagonal(*off));

  std::vector<TargetSpec> one(1);
  one[0].name = "jawOpen";
  one[0].mesh = jaw;
  one[0].mask.assign(n, 1.0);
  one[0].inbetweens.push_back({0.5, jaw});
  one[0].inbetweens[0].mesh.vertices = rest.vertices + 0.7 * (jaw.vertices - rest.vertices);
  const auto rig = Rig::Build(rest, std::move(one), options);
  const double tolerance = kShapeTolerance * Diagonal(*rig);
  EXPECT_LE(MaxDistance(SolveFrame(rig, {0.5}), rest.vertices + 0.7 * (jaw.vertices - rest.vertices)), tolerance);
  EXPECT_LE(MaxDistance(SolveFrame(rig, {1.0}), jaw.vertices), tolerance);
}

// Each bad spec: the error names the target and the field.
TEST(ProductionRig, BadSpecsAreRefusedNamingTargetAndField) {
  const auto build = [](std::vector<TargetSpec> specs) {
    return CatchError([&] { Rig::Build(Rest("cylinder/cylinder.obj"), std::move(specs)); });
  };
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].mask.assign(419, 1.0);
    EXPECT_THAT(build(std::move(specs)).what(), AllOf(HasSubstr("target 'bend'"), HasSubstr("mask has 419 values")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].inbetweens.push_back({1.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'bend'"), HasSubstr("inbetweens[0].weight = 1.5 is outside (0, 1)")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
    specs[0].inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-3.obj"))});
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'bend'"), HasSubstr("inbetweens[1].weight = 0.5 is repeated")));
  }
  // In-betweens a spacing from 0, 1 and each other: their blend's slope is 1 / the gap (1e-300 gave 1e300).
  for (const double weight : {1e-300, 1.0 - 1e-16}) {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].inbetweens.push_back({weight, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'bend'"), HasSubstr("inbetweens[0].weight"),
                      HasSubstr(weight < 0.5 ? "within 1e-06 of 0" : "within 1e-06 of 1")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
    specs[0].inbetweens.push_back({0.5 + 1e-9, LoadMesh(DataPath("cylinder/poses-2_cylinder-3.obj"))});
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'bend'"), HasSubstr("inbetweens[1].weight"),
                      HasSubstr("within 1e-06 of inbetweens[0].weight = 0.5")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].mask.assign(specs[0].mesh.vertices.rows(), 1.0);
    specs[0].mask[7] = 1e9;
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'bend'"), HasSubstr("mask[7] = 1000000000 is beyond +-1000")));
  }
  {
    std::vector<TargetSpec> specs = CylinderCombination();
    specs[2].combination = {"a", "missing"};
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'a_b'"), HasSubstr("combination[1] = 'missing' is not a target")));
  }
  {
    std::vector<TargetSpec> specs = CylinderCombination();
    TargetSpec nested = Spec("a_b_a", "cylinder/poses-2_cylinder-2.obj");
    nested.combination = {"a_b", "a"};
    specs.push_back(std::move(nested));
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'a_b_a'"), HasSubstr("combination[0] = 'a_b' is a combination")));
  }
  {
    std::vector<TargetSpec> specs = CylinderCombination();
    specs[2].combination = {"a"};
    EXPECT_THAT(build(std::move(specs)).what(), AllOf(HasSubstr("target 'a_b'"), HasSubstr("at least two drivers")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].inbetweens.push_back({0.5, LoadMesh(DataPath("cube/cube.obj"))});
    EXPECT_THAT(build(std::move(specs)).what(), HasSubstr("cube.obj: target 'bend@0.5' has 1538 vertices"));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-3.obj"));
    EXPECT_THAT(build(std::move(specs)).what(), AllOf(HasSubstr("target 'bend'"), HasSubstr("name is used twice")));
  }
}

// The weights a frame may give (ValidateWeights, which Solve, the blend helpers and the CLI's local blend call):
// each within +-kMaxTargetWeight, a combination's product of them too, and the shapes' effective weights (an
// in-between extrapolates with its last segment's slope) within +-kMaxShapeWeight.
// A target (or in-between), times its mask, that takes a vertex more than kMaxTargetReach diagonals from the
// rest shape is refused before any spring is built (a mask of -1000 made one tiny upload solve for 100 s).
TEST(ProductionRig, TargetsFarOutsideTheRestShapeAreRefusedNamingTargetAndVertex) {
  const TriangleMesh rest = Rest("cylinder/cylinder.obj");
  const double diagonal = BoundingBoxDiagonal(rest.vertices);
  const auto build = [&](std::vector<TargetSpec> specs) {
    return CatchError([&] { Rig::Build(rest, std::move(specs)); });
  };
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].mesh.vertices(7, 1) += 20 * diagonal;
    EXPECT_THAT(build(std::move(specs)).what(),
                AllOf(HasSubstr("target 'bend': vertex 7 moves"), HasSubstr("more than 10 times the rest mesh's "
                                                                             "bounding-box diagonal")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].mask.assign(static_cast<size_t>(rest.vertices.rows()), -1000.0);  // within the mask's own bound
    EXPECT_THAT(build(std::move(specs)).what(), AllOf(HasSubstr("target 'bend': vertex"), HasSubstr("with its mask 1000")));
  }
  {
    std::vector<TargetSpec> specs;
    specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
    specs[0].inbetweens.push_back({0.5, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
    specs[0].inbetweens[0].mesh.vertices.row(3).array() -= 50 * diagonal;
    EXPECT_THAT(build(std::move(specs)).what(), HasSubstr("target 'bend': inbetweens[0]: vertex 3 moves"));
  }
  // A large but sane move (a limb swung across the body) is accepted.
  std::vector<TargetSpec> specs;
  specs.push_back(Spec("bend", "cylinder/poses-2_cylinder-4.obj"));
  specs[0].mesh.vertices(7, 1) += 2 * diagonal;
  RigOptions options;
  options.target_paths = false;
  EXPECT_NO_THROW(Rig::Build(rest, std::move(specs), options));
}

TEST(ProductionRig, WeightsWhoseShapesWouldOverflowAreRefused) {
  RigOptions options;
  options.target_paths = false;
  const auto combination = Rig::Build(Rest("cylinder/cylinder.obj"), CylinderCombination(), options);
  EXPECT_THAT(CatchError([&] { ValidateWeights(*combination, {100, 100}); }).what(),
              HasSubstr("combination 'a_b' has weight 10000 (the product of its drivers' weights), beyond +-1000"));
  EXPECT_THAT(CatchError([&] { LinearBlend(*combination, {2000, 0}); }).what(),
              HasSubstr("weights[0] (target 'a') = 2000 is beyond +-1000"));
  EXPECT_NO_THROW(ValidateWeights(*combination, {30, -30}));

  TargetSpec bend = Spec("bend", "cylinder/poses-2_cylinder-4.obj");
  bend.inbetweens.push_back({1.0 - 1e-4, LoadMesh(DataPath("cylinder/poses-2_cylinder-2.obj"))});
  std::vector<TargetSpec> specs;
  specs.push_back(std::move(bend));
  const auto steep = Rig::Build(Rest("cylinder/cylinder.obj"), std::move(specs), options);
  // Past 1 the last segment's slope is 1e4: weight 1000 gives the full shape about 1e7.
  EXPECT_THAT(CatchError([&] { ValidateWeights(*steep, {1000}); }).what(),
              AllOf(HasSubstr("sculpted shape 0 (bend)"), HasSubstr("beyond +-1e+06")));
  EXPECT_NO_THROW(ValidateWeights(*steep, {1.0}));
}

}  // namespace
}  // namespace springblend
