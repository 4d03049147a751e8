// The rig's volume and the internal anchor (paper sections 3.1 and 3.4) on the closed bundled meshes and the
// capped cylinder: exact shapes with the anchor active, volume kept better than linear blending, a rigid
// anchor, pins, and the rig summary the paper's Table 1 reports.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <set>

#include "anchor.h"
#include "rigid.h"
#include "springblend/solve.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::LoadRig;
using testing::MaxDistance;

// Volume enclosed by a closed, outward-oriented triangle surface (divergence theorem).
double EnclosedVolume(const Points& x, const Faces& faces) {
  double six_v = 0.0;
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    const Eigen::Vector3d a = x.row(faces(f, 0)).transpose();
    const Eigen::Vector3d b = x.row(faces(f, 1)).transpose();
    const Eigen::Vector3d c = x.row(faces(f, 2)).transpose();
    six_v += a.dot(b.cross(c));
  }
  return six_v / 6.0;
}

struct ClosedCase {
  const char* rest;
  const char* target;
  int frames;
};

// Readable in ctest's output (gtest prints a parameter without PrintTo as raw bytes).
void PrintTo(const ClosedCase& c, std::ostream* os) { *os << std::string(c.rest) + " -> " + c.target; }

// The anchor, the interior and the volume: no target paths (they do not depend on where a frame's solve starts).
class ClosedRig : public ::testing::TestWithParam<ClosedCase> {};

TEST_P(ClosedRig, AlphaZeroAndOneReproduceRestAndTargetWithTheAnchorActive) {
  auto rig = LoadRig(GetParam().rest, {GetParam().target}, testing::NoPathsRigOptions());
  const RigSummary& s = rig->summary();
  ASSERT_EQ(s.interior, "closed") << s.interior_reason;
  ASSERT_EQ(rig->boundary_mode(), BoundaryMode::kAnchored);
  EXPECT_GT(s.interior_vertices, 0);
  EXPECT_GE(s.anchor_vertices, 3);
  EXPECT_GT(s.tetrahedra, 0);
  const double tolerance = 1e-6 * s.bounding_box_diagonal;
  for (double alpha : {0.0, 1.0}) {
    Solver solver(rig);
    Points x;
    const SolveSummary summary = solver.Solve({{alpha}}, &x);
    ASSERT_TRUE(summary.converged()) << summary.message;
    EXPECT_EQ(summary.fixed_vertices, s.anchor_vertices);
    EXPECT_LE(MaxDistance(x, alpha == 0.0 ? rig->rest().vertices : rig->target(0).vertices), tolerance);
    EXPECT_LE(MaxDistance(solver.all_positions(), rig->shape(alpha == 0.0 ? 0 : 1)), tolerance);
  }
}

TEST(ClosedCube, SweepWithTheAnchorEndsExactlyOnTheTarget) {
  auto rig = LoadRig("cube/cube.obj", {"cube/poses-1_cube-4.obj"}, testing::NoPathsRigOptions());
  Solver solver(rig);
  Points x;
  const auto frames = SweepFrames({1.0}, 6);
  for (size_t i = 0; i < frames.size(); ++i) {
    const SolveSummary summary = solver.Solve(frames[i], &x);
    ASSERT_TRUE(summary.converged()) << "frame " << i << ": " << summary.message;
    EXPECT_LE(summary.residual, solver.options().residual_tolerance);
  }
  EXPECT_LE(MaxDistance(x, rig->target(0).vertices), 1e-6 * rig->summary().bounding_box_diagonal);
}

TEST_P(ClosedRig, KeepsTheBlendedVolumeCloserThanLinearBlending) {
  auto rig = LoadRig(GetParam().rest, {GetParam().target}, testing::NoPathsRigOptions());
  const Faces& faces = rig->rest().faces;
  const double v0 = EnclosedVolume(rig->rest().vertices, faces);
  const double v1 = EnclosedVolume(rig->target(0).vertices, faces);
  Solver solver(rig);
  Points x;
  for (const auto& frame : SweepFrames({0.5}, 3)) ASSERT_TRUE(solver.Solve(frame, &x).converged());
  const double expected = 0.5 * (v0 + v1);
  const double physical = std::abs(EnclosedVolume(x, faces) - expected);
  const double linear = std::abs(EnclosedVolume(LinearBlend(*rig, {0.5}), faces) - expected);
  EXPECT_LT(physical, linear) << "volume error: springs " << physical << ", linear " << linear
                              << " (of " << expected << ")";
}

TEST_P(ClosedRig, TheAnchorMovesRigidly) {
  auto rig = LoadRig(GetParam().rest, {GetParam().target}, testing::NoPathsRigOptions());
  const auto& anchor = rig->anchor_vertices();
  ASSERT_GE(anchor.size(), 3u);
  Points rest(static_cast<Eigen::Index>(anchor.size()), 3);
  for (size_t i = 0; i < anchor.size(); ++i) rest.row(static_cast<Eigen::Index>(i)) = rig->shape(0).row(anchor[i]);
  for (double w : {0.3, 0.7, 1.0}) {
    Solver solver(rig);
    Points x;
    ASSERT_TRUE(solver.Solve({{w}}, &x).converged());
    Points moved(rest.rows(), 3);
    for (size_t i = 0; i < anchor.size(); ++i) {
      moved.row(static_cast<Eigen::Index>(i)) = solver.all_positions().row(anchor[i]);
    }
    // Rigid: every pairwise distance is kept to round-off.
    for (Eigen::Index i = 0; i < rest.rows(); ++i) {
      for (Eigen::Index j = i + 1; j < rest.rows(); ++j) {
        EXPECT_NEAR((moved.row(i) - moved.row(j)).norm(), (rest.row(i) - rest.row(j)).norm(),
                    1e-12 * rig->summary().bounding_box_diagonal);
      }
    }
  }
}

INSTANTIATE_TEST_SUITE_P(
    BundledClosedMeshes, ClosedRig,
    ::testing::Values(ClosedCase{"cube/cube.obj", "cube/poses-1_cube-4.obj", 6},
                      ClosedCase{"cheburashka/cheburashka.obj", "cheburashka/poses-1_cheburashka-1.obj", 3}),
    [](const ::testing::TestParamInfo<ClosedCase>& param) {
      const std::string rest = param.param.rest;
      return rest.substr(0, rest.find('/'));
    });

TEST(AnchorMotion, BlendsAlongTheGeodesicAndAveragesMany) {
  internal::AnchorMotion quarter_turn;
  quarter_turn.rotation = Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()));
  quarter_turn.offset = Eigen::Vector3d(2, 0, 0);
  const auto half = internal::BlendAnchorMotions({quarter_turn}, {0.5});
  EXPECT_NEAR(Eigen::AngleAxisd(half.rotation).angle(), M_PI / 4, 1e-12);
  EXPECT_NEAR(half.offset.x(), 1.0, 1e-12);
  const auto beyond = internal::BlendAnchorMotions({quarter_turn}, {1.5});  // extrapolates
  EXPECT_NEAR(Eigen::AngleAxisd(beyond.rotation).angle(), 3 * M_PI / 4, 1e-12);
  // Two targets with equal weights and opposite rotations average to the identity.
  internal::AnchorMotion other = quarter_turn;
  other.rotation = quarter_turn.rotation.inverse();
  const auto both = internal::BlendAnchorMotions({quarter_turn, other}, {0.5, 0.5});
  EXPECT_NEAR(both.rotation.angularDistance(Eigen::Quaterniond::Identity()), 0.0, 1e-12);
  // A weight of one reproduces that target's motion.
  const auto exact = internal::BlendAnchorMotions({quarter_turn, other}, {0.0, 1.0});
  EXPECT_NEAR(exact.rotation.angularDistance(other.rotation), 0.0, 1e-12);
}

TEST(CappedCylinder, HolesAreClosedAndBendsReachTheirTargets) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-2.obj"});
  const RigSummary& s = rig->summary();
  EXPECT_EQ(s.interior, "capped");
  EXPECT_EQ(s.cap_vertices, 2);
  EXPECT_THAT(s.interior_reason, HasSubstr("2 holes closed"));
  EXPECT_EQ(s.vertices, s.surface_vertices + s.cap_vertices + s.interior_vertices);
  // Surface-only, this bend settles in a dimpled equilibrium (see solve_test); with volume it does not.
  Solver solver(rig);
  Points x;
  for (const auto& frame : SweepFrames({1.0}, 12)) ASSERT_TRUE(solver.Solve(frame, &x).converged());
  EXPECT_LE(MaxDistance(x, rig->target(0).vertices), 1e-6 * s.bounding_box_diagonal);
}

TEST(RigSummary, ReportsWhatThePapersTableReports) {
  auto rig = LoadRig("cube/cube.obj", {"cube/poses-1_cube-4.obj"}, testing::NoPathsRigOptions());
  const RigSummary& s = rig->summary();
  EXPECT_EQ(s.surface_vertices, 1538);
  EXPECT_EQ(s.vertices, s.surface_vertices + s.interior_vertices);
  int by_kind = 0;
  for (int k = 0; k < kSpringKindCount; ++k) by_kind += s.springs_by_kind[k];
  EXPECT_EQ(by_kind, s.springs);
  EXPECT_GT(s.springs_by_kind[static_cast<int>(SpringKind::kInternal)], 0);
  EXPECT_EQ(s.tetrahedra, rig->tetrahedra().rows());
  EXPECT_GT(s.precompute_ms, 0.0);
  // TetGen's tetrahedra are positively oriented at rest; the targets' placed interiors may invert some
  // (the paper's limit), and the summary counts them.
  EXPECT_EQ(internal::CountInvertedTetrahedra(rig->tetrahedra(), rig->shape(0)), 0);
  EXPECT_EQ(internal::CountInvertedTetrahedra(rig->tetrahedra(), rig->shape(1)), s.inverted_tetrahedra_in_targets);
  EXPECT_LT(s.inverted_tetrahedra_in_targets, s.tetrahedra / 20);
}

namespace {

// A cylinder with one end's faces flipped cannot be tetrahedralized.
std::pair<TriangleMesh, TriangleMesh> FlippedCylinder() {
  TriangleMesh rest = LoadMesh(testing::DataPath("cylinder/cylinder.obj"));
  TriangleMesh target = LoadMesh(testing::DataPath("cylinder/poses-2_cylinder-1.obj"));
  for (Eigen::Index f = 0; f < 40; ++f) {
    std::swap(rest.faces(f, 0), rest.faces(f, 1));
    std::swap(target.faces(f, 0), target.faces(f, 1));
  }
  return {rest, target};
}

}  // namespace

TEST(Interior, FallsBackToSurfaceSpringsAndSaysWhy) {
  auto [rest, target] = FlippedCylinder();
  RigOptions options;
  options.shell = false;
  auto rig = Rig::Build(rest, {target}, options);
  EXPECT_EQ(rig->summary().interior, "surface");
  EXPECT_THAT(rig->summary().interior_reason, HasSubstr("surface springs only"));
  EXPECT_EQ(rig->num_vertices(), 420);
  Points x;
  EXPECT_TRUE(Solver(rig).Solve({{0.5}}, &x).converged());
}

TEST(Shell, AnOpenSurfaceWithoutInteriorGetsAnInnerLayerAndStillReproducesItsTargets) {
  auto [rest, target] = FlippedCylinder();
  auto rig = Rig::Build(rest, {target});
  const RigSummary& s = rig->summary();
  EXPECT_EQ(s.interior, "shell");
  EXPECT_THAT(s.interior_reason, HasSubstr("inner layer"));
  EXPECT_EQ(s.shell_vertices, 420);
  EXPECT_EQ(rig->num_vertices(), 840);
  // Every shape of the system, the layer included, is unstressed: its own rest lengths are its lengths.
  for (int shape = 0; shape <= 1; ++shape) {
    const Points& x = rig->shape(shape);
    for (int q = 0; q < rig->num_springs(); ++q) {
      const double length = (x.row(rig->spring_a()[q]) - x.row(rig->spring_b()[q])).norm();
      const double rest_length = rig->rest_lengths()[q] + (shape == 0 ? 0.0 : rig->rest_length_delta(0)[q]);
      ASSERT_NEAR(length, rest_length, 1e-12) << "spring " << q << " in shape " << shape;
    }
  }
  // Each inner vertex sits as deep as its surface vertex's edges are long on average, at most the mean edge
  // length (where the mesh is fine, as at a mouth corner's crease, a uniform depth folds the layer over itself).
  const Points& x = rig->shape(0);
  std::vector<double> incident(420, 0.0);
  std::vector<int> count(420, 0);
  double mean = 0.0;
  int edges = 0;
  std::set<std::pair<int, int>> seen;  // each edge once
  for (Eigen::Index f = 0; f < rest.faces.rows(); ++f) {
    for (int c = 0; c < 3; ++c) {
      const int a = rest.faces(f, c), b = rest.faces(f, (c + 1) % 3);
      if (!seen.insert({std::min(a, b), std::max(a, b)}).second) continue;
      const double length = (rest.vertices.row(a) - rest.vertices.row(b)).norm();
      incident[a] += length, incident[b] += length;
      ++count[a], ++count[b];
      mean += length;
      ++edges;
    }
  }
  mean /= edges;
  int thinner = 0;
  for (int v = 0; v < 420; ++v) {
    const double depth = std::min(mean, incident[v] / count[v]);
    EXPECT_NEAR((x.row(v) - x.row(420 + v)).norm(), depth, 1e-9 * depth) << "vertex " << v;
    thinner += depth < mean ? 1 : 0;
  }
  EXPECT_GT(thinner, 0);
  Solver solver(rig);
  Points solved;
  ASSERT_TRUE(solver.Solve({{1.0}}, &solved).converged());
  const double diagonal = BoundingBoxDiagonal(rest.vertices);
  EXPECT_LT((solved - target.vertices).rowwise().norm().maxCoeff(), 1e-6 * diagonal);
  ASSERT_TRUE(solver.Solve({{0.0}}, &solved).converged());
  EXPECT_LT((solved - rest.vertices).rowwise().norm().maxCoeff(), 1e-6 * diagonal);
}

TEST(Pins, APinnedVertexSitsExactlyAtItsPinAndItsNeighboursFollow) {
  auto rig = LoadRig("cube/cube.obj", {"cube/poses-1_cube-4.obj"}, testing::NoPathsRigOptions());
  Solver solver(rig);
  Points free_x, pinned_x;
  ASSERT_TRUE(solver.Solve({{0.3}}, &free_x).converged());
  const int v = 628;
  const Eigen::Vector3d target = free_x.row(v).transpose() + Eigen::Vector3d(-0.3, 0.1, 0.0);
  Frame frame{{0.3}, {Pin{v, target}}};
  const SolveSummary s = solver.Solve(frame, &pinned_x);
  ASSERT_TRUE(s.converged()) << s.message;
  EXPECT_EQ(s.pins, 1);
  EXPECT_EQ(pinned_x.row(v).transpose(), target);
  // Its one-ring moves with it, less than it does; far vertices barely move.
  const double pull = (target - free_x.row(v).transpose()).norm();
  for (int e = rig->vertex_spring_offsets()[v]; e < rig->vertex_spring_offsets()[v + 1]; ++e) {
    const int q = rig->vertex_springs()[e];
    if (rig->spring_kind()[q] != SpringKind::kStructure) continue;
    const int o = rig->spring_a()[q] == v ? rig->spring_b()[q] : rig->spring_a()[q];
    const double moved = (pinned_x.row(o) - free_x.row(o)).norm();
    EXPECT_GT(moved, 0.05 * pull) << "neighbour " << o;
    EXPECT_LT(moved, pull) << "neighbour " << o;
  }
  EXPECT_THAT(testing::CatchError([&] { solver.Solve({{0.3}, {Pin{100000, target}}}, &pinned_x); }).what(),
              HasSubstr("pins[0].vertex = 100000"));
}

}  // namespace
}  // namespace springblend
