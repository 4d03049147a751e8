// Physical interaction (paper section 4): obstacles of every kind, contacts that keep the blended shape
// out of them in every frame, contacts that release when the obstacle leaves, and refusals.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>

#include "springblend/collider.h"
#include "springblend/solve.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CatchError;
using testing::LoadRig;
using testing::MaxDistance;

// The paper's Fig. 2 set-up rebuilt on the cylinder: one end stays, the free end bends up through this
// ball when nothing stops it.
const Eigen::Vector3d kBallCenter(-1.7, 0.75, 0.75);
constexpr double kBallRadius = 0.35;

std::shared_ptr<const Rig> BendingCylinder() {
  return LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
}

// Generalized winding number of a closed mesh at p (1 inside, 0 outside): an independent inside test.
double WindingNumber(const TriangleMesh& mesh, const Eigen::Vector3d& p) {
  double total = 0.0;
  for (Eigen::Index f = 0; f < mesh.faces.rows(); ++f) {
    const Eigen::Vector3d a = mesh.vertices.row(mesh.faces(f, 0)).transpose() - p;
    const Eigen::Vector3d b = mesh.vertices.row(mesh.faces(f, 1)).transpose() - p;
    const Eigen::Vector3d c = mesh.vertices.row(mesh.faces(f, 2)).transpose() - p;
    const double la = a.norm(), lb = b.norm(), lc = c.norm();
    total += 2.0 * std::atan2(a.dot(b.cross(c)), la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb);
  }
  return total / (4.0 * M_PI);
}

// Spot the cow, scaled and moved to sit where the ball sits.
TriangleMesh SpotObstacle() {
  TriangleMesh spot = LoadMesh(testing::DataPath("spot/spot_low_resolution.obj"));
  const Eigen::RowVector3d center = 0.5 * (spot.vertices.colwise().maxCoeff() + spot.vertices.colwise().minCoeff());
  const double size = (spot.vertices.colwise().maxCoeff() - spot.vertices.colwise().minCoeff()).maxCoeff();
  spot.vertices = ((spot.vertices.rowwise() - center) * (2.2 * kBallRadius / size)).rowwise() + kBallCenter.transpose();
  return spot;
}

struct SweepResult {
  double deepest = 0.0;  // largest penetration over all frames
  int frames_with_contacts = 0;
  bool all_converged = true;
};

template <typename Depth>
SweepResult Sweep(const std::shared_ptr<const Rig>& rig, std::vector<Collider> colliders, Depth depth) {
  Solver solver(rig);
  solver.SetColliders(std::move(colliders));
  SweepResult result;
  Points x;
  for (const auto& frame : SweepFrames({1.0}, 8)) {
    const SolveSummary s = solver.Solve(frame, &x);
    result.all_converged = result.all_converged && s.converged();
    result.frames_with_contacts += s.contacts > 0;
    for (Eigen::Index v = 0; v < x.rows(); ++v) result.deepest = std::max(result.deepest, depth(x.row(v).transpose()));
  }
  return result;
}

TEST(Contacts, TheBendingCylinderNeverEntersTheBall) {
  auto rig = BendingCylinder();
  auto depth = [](const Eigen::Vector3d& p) { return kBallRadius - (p - kBallCenter).norm(); };
  const SweepResult free = Sweep(rig, {}, depth);
  const SweepResult blocked = Sweep(rig, {Collider::Sphere(kBallCenter, kBallRadius)}, depth);
  EXPECT_GT(free.deepest, 0.1) << "the ball must stand in the free bend's path";
  EXPECT_TRUE(blocked.all_converged);
  EXPECT_GT(blocked.frames_with_contacts, 0);
  EXPECT_LE(blocked.deepest, 1e-6 * rig->summary().bounding_box_diagonal);
}

TEST(Contacts, AMeshObstacleBlocksTheSameWay) {
  auto rig = BendingCylinder();
  const TriangleMesh spot = SpotObstacle();
  // Depth proxy for a mesh: 1 when inside by the winding number, else 0.
  auto inside = [&](const Eigen::Vector3d& p) { return WindingNumber(spot, p) > 0.5 ? 1.0 : 0.0; };
  const SweepResult free = Sweep(rig, {}, inside);
  const SweepResult blocked = Sweep(rig, {Collider::Mesh(spot)}, inside);
  EXPECT_EQ(free.deepest, 1.0) << "spot must stand in the free bend's path";
  EXPECT_TRUE(blocked.all_converged);
  EXPECT_GT(blocked.frames_with_contacts, 0);
  EXPECT_EQ(blocked.deepest, 0.0);
}

TEST(Contacts, ReleaseWhenTheObstacleMovesAway) {
  auto rig = BendingCylinder();
  Solver solver(rig);
  solver.SetColliders({Collider::Sphere(kBallCenter, kBallRadius)});
  Points x;
  for (const auto& frame : SweepFrames({0.7}, 5)) ASSERT_TRUE(solver.Solve(frame, &x).converged());
  Frame here{{0.7}};
  const SolveSummary blocked = solver.Solve(here, &x);
  ASSERT_GT(blocked.contacts, 0);
  Frame away{{0.7}, {}, {RigidTransform{Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, 10)}}};
  const SolveSummary released = solver.Solve(away, &x);
  ASSERT_TRUE(released.converged()) << released.message;
  EXPECT_EQ(released.contacts, 0);
  Points reference;
  ASSERT_TRUE(Solver(rig).Solve({{0.7}}, &reference).converged());
  EXPECT_LE(MaxDistance(x, reference), 1e-6 * rig->summary().bounding_box_diagonal);
}

TEST(Contacts, TheObstacleFollowsItsPerFrameMotion) {
  auto rig = BendingCylinder();
  // The same ball, defined away from the path and moved into it by the frame's transform.
  const Eigen::Vector3d elsewhere = kBallCenter + Eigen::Vector3d(0, 0, 5);
  // Both converged far below the default tolerance, so the comparison shows the two are the same problem.
  SolveOptions tight;
  tight.residual_tolerance = 1e-11;
  tight.step_tolerance = 1e-10;
  Solver moved(rig, tight);
  moved.SetColliders({Collider::Sphere(elsewhere, kBallRadius)});
  Solver placed(rig, tight);
  placed.SetColliders({Collider::Sphere(kBallCenter, kBallRadius)});
  Points a, b;
  const RigidTransform into_path{Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, -5)};
  for (const auto& frame : SweepFrames({0.8}, 5)) {
    Frame f = frame;
    f.collider_transforms = {into_path};
    ASSERT_TRUE(moved.Solve(f, &a).converged());
    ASSERT_TRUE(placed.Solve(frame, &b).converged());
  }
  EXPECT_LE(MaxDistance(a, b), 1e-9 * rig->summary().bounding_box_diagonal);
}

TEST(Collider, EachShapeProjectsOntoItsSurfaceWithAnOutwardNormal) {
  const RigidTransform none;
  Eigen::Vector3d s, n;
  // Sphere.
  const Collider sphere = Collider::Sphere({0, 0, 0}, 1.0);
  ASSERT_TRUE(sphere.Penetrates({0.5, 0, 0}, none, &s, &n));
  EXPECT_TRUE(s.isApprox(Eigen::Vector3d(1, 0, 0)));
  EXPECT_TRUE(n.isApprox(Eigen::Vector3d(1, 0, 0)));
  EXPECT_FALSE(sphere.Penetrates({1.5, 0, 0}, none, &s, &n));
  // Capsule along x from 0 to 2, radius 0.5.
  const Collider capsule = Collider::Capsule({0, 0, 0}, {2, 0, 0}, 0.5);
  ASSERT_TRUE(capsule.Penetrates({1, 0.2, 0}, none, &s, &n));
  EXPECT_TRUE(s.isApprox(Eigen::Vector3d(1, 0.5, 0)));
  ASSERT_TRUE(capsule.Penetrates({2.3, 0, 0}, none, &s, &n));  // the round end
  EXPECT_TRUE(s.isApprox(Eigen::Vector3d(2.5, 0, 0)));
  EXPECT_FALSE(capsule.Penetrates({1, 0.6, 0}, none, &s, &n));
  // Box: leaves through the nearest face.
  const Collider box = Collider::Box({0, 0, 0}, {1, 2, 3});
  ASSERT_TRUE(box.Penetrates({0.8, 0.1, 0.1}, none, &s, &n));
  EXPECT_TRUE(s.isApprox(Eigen::Vector3d(1, 0.1, 0.1)));
  EXPECT_TRUE(n.isApprox(Eigen::Vector3d(1, 0, 0)));
  EXPECT_FALSE(box.Penetrates({0, 2.5, 0}, none, &s, &n));
  // Plane z = 1 with normal +z: solid below.
  const Collider plane = Collider::Plane({0, 0, 1}, {0, 0, 2});
  ASSERT_TRUE(plane.Penetrates({3, 4, 0.5}, none, &s, &n));
  EXPECT_TRUE(s.isApprox(Eigen::Vector3d(3, 4, 1)));
  EXPECT_FALSE(plane.Penetrates({3, 4, 1.5}, none, &s, &n));
  // A moved box: rotated a quarter turn about z and shifted.
  const RigidTransform turn{Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ())),
                            Eigen::Vector3d(10, 0, 0)};
  ASSERT_TRUE(box.Penetrates({10 - 1.9, 0.0, 0.0}, turn, &s, &n));  // local y = 1.9 of half extent 2
  EXPECT_TRUE(s.isApprox(Eigen::Vector3d(8, 0, 0)));
  EXPECT_TRUE(n.isApprox(Eigen::Vector3d(-1, 0, 0)));
}

TEST(Collider, MeshInsideTestAgreesWithTheWindingNumber) {
  const TriangleMesh spot = SpotObstacle();
  const Collider collider = Collider::Mesh(spot);
  const RigidTransform none;
  int inside = 0;
  for (int i = 0; i < 200; ++i) {
    const Eigen::Vector3d p = kBallCenter + 0.5 * kBallRadius * Eigen::Vector3d::Random();
    Eigen::Vector3d s, n;
    const bool penetrates = collider.Penetrates(p, none, &s, &n);
    EXPECT_EQ(penetrates, WindingNumber(spot, p) > 0.5) << p.transpose();
    if (penetrates) {
      ++inside;
      EXPECT_GT(n.dot(s - p), 0.0);  // the normal points from the point out to the surface
    }
  }
  EXPECT_GT(inside, 10);
}

// A closed 4-vertex "tetrahedron" whose corners lie on one line, or at one point: CGAL's Side_of_triangle_mesh
// retried rays for ever on it (issue 19). Now refused before any CGAL call, naming the problem.
TEST(Collider, DegenerateMeshesAreRefusedNotLoopedOn) {
  const std::string faces = "f 1 2 3\nf 1 4 2\nf 2 4 3\nf 3 4 1\n";
  const auto refusal = [&](const std::string& vertices) {
    return std::string(CatchError([&] { Collider::Mesh(LoadMeshFromText(vertices + faces, "obj", "c.obj")); }).what());
  };
  EXPECT_THAT(refusal("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\n"), HasSubstr("degenerate"));
  EXPECT_THAT(refusal("v 1 1 1\nv 1 1 1\nv 1 1 1\nv 1 1 1\n"), HasSubstr("degenerate"));
  EXPECT_THAT(refusal("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"), HasSubstr("degenerate"));  // flat
  // Non-manifold: two faces use one edge in the same direction.
  EXPECT_THAT(refusal("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n" + std::string("f 1 2 3\n")),
              HasSubstr("same direction"));
  // A valid tetrahedron is taken, and its inside test answers.
  const Collider tet = Collider::Mesh(LoadMeshFromText("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
                                                       "f 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n", "obj", "t.obj"));
  Eigen::Vector3d s, n;
  EXPECT_TRUE(tet.Penetrates({0.1, 0.1, 0.1}, RigidTransform{}, &s, &n));
  EXPECT_FALSE(tet.Penetrates({1.0, 1.0, 1.0}, RigidTransform{}, &s, &n));
  // Points exactly on a vertex, an edge or in a face's plane through an edge: bounded, whatever the answer.
  for (const Eigen::Vector3d& p : {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(0.5, 0, 0), Eigen::Vector3d(-1, 0, 0),
                                  Eigen::Vector3d(0.25, 0.25, 0), Eigen::Vector3d(-1, -1, -1)}) {
    tet.Penetrates(p, RigidTransform{}, &s, &n);
  }
}

TEST(Collider, MeshCapsAreCheckedBeforeCgal) {
  const TriangleMesh spot = SpotObstacle();
  MeshColliderLimits few;
  few.max_vertices = 100;
  EXPECT_THAT(CatchError([&] { Collider::Mesh(spot, few); }).what(), HasSubstr("over the limit of 100"));
  MeshColliderLimits low_valence;
  low_valence.max_valence = 3;
  EXPECT_THAT(CatchError([&] { Collider::Mesh(spot, low_valence); }).what(), HasSubstr("valence"));
}

TEST(Collider, APlaneWhoseNormalOverflowsIsRefused) {
  EXPECT_THAT(CatchError([] { Collider::Plane({0, 0, 0}, {1e200, 1e200, 1e200}); }).what(), HasSubstr("overflows"));
  EXPECT_EQ(Collider::Plane({0, 0, 0}, {0, 1e100, 0}).shape(), Collider::Shape::kPlane);
}

TEST(Contacts, RefusedForARigWithNothingToHoldIt) {
  RigOptions surface_only;
  surface_only.interior = false;
  auto floating = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-1.obj"}, surface_only);
  Solver solver(floating);
  EXPECT_THAT(CatchError([&] { solver.SetColliders({Collider::Sphere(kBallCenter, kBallRadius)}); }).what(),
              HasSubstr("fixed vertices or an internal anchor"));
}

TEST(Contacts, AWrongNumberOfColliderTransformsIsRefused) {
  auto rig = BendingCylinder();
  Solver solver(rig);
  solver.SetColliders({Collider::Sphere(kBallCenter, kBallRadius)});
  Points x;
  Frame frame{{0.5}, {}, {RigidTransform{}, RigidTransform{}}};
  EXPECT_THAT(CatchError([&] { solver.Solve(frame, &x); }).what(),
              HasSubstr("collider_transforms has 2 entries but there are 1 colliders"));
}

}  // namespace
}  // namespace springblend
