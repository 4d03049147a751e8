// Building rigs: springs, rest lengths, boundary conditions, and refusals of mismatched targets.
#include "springblend/rig.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <set>

#include "rig_internals.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CatchError;
using testing::DataPath;
using testing::LoadRig;

TEST(Rig, CylinderSpringsFollowTheMeshTopology) {
  RigOptions surface_only = testing::NoPathsRigOptions();
  surface_only.interior = false;
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, surface_only);
  const RigSummary& s = rig->summary();
  EXPECT_EQ(s.interior, "surface");
  EXPECT_EQ(s.springs_by_kind[static_cast<int>(SpringKind::kInternal)], 0);
  // An open tube of 20 rings x 21 columns: E = V + F - chi with chi = 0 for an annulus.
  EXPECT_EQ(s.springs_by_kind[static_cast<int>(SpringKind::kStructure)], 420 + 800);
  // One bending spring per interior edge; the two rims (40 boundary edges) have none.
  EXPECT_EQ(s.boundary_edges, 40);
  EXPECT_EQ(s.springs_by_kind[static_cast<int>(SpringKind::kBending)], 1220 - 40);
  EXPECT_EQ(s.springs, rig->num_springs());
  EXPECT_EQ(s.vertices, 420);
  // Rest lengths are the rest shape's edge lengths; target deltas give the target's.
  const Points& x0 = rig->shape(0);
  const Points& x1 = rig->shape(1);
  for (int q = 0; q < rig->num_springs(); q += 37) {
    const int a = rig->spring_a()[q], b = rig->spring_b()[q];
    ASSERT_LT(a, b);
    EXPECT_NEAR(rig->rest_lengths()[q], (x0.row(a) - x0.row(b)).norm(), 1e-12);
    EXPECT_NEAR(rig->rest_lengths()[q] + rig->rest_length_delta(0)[q], (x1.row(a) - x1.row(b)).norm(), 1e-12);
  }
}

TEST(Rig, NoSpringIsDuplicated) {
  auto rig = LoadRig("cube/cube.obj", {"cube/poses-1_cube-1.obj"}, testing::NoPathsRigOptions());
  std::set<std::pair<int, int>> pairs;
  for (int q = 0; q < rig->num_springs(); ++q) {
    EXPECT_TRUE(pairs.insert({rig->spring_a()[q], rig->spring_b()[q]}).second);
  }
  EXPECT_EQ(rig->summary().boundary_edges, 0);  // the cube is closed
}

TEST(Rig, DetectsStaticVerticesAcrossAllTargets) {
  // poses-2_cylinder-1 keeps one end still: 194 vertices move less than 1e-6 of the diagonal.
  auto one = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, testing::NoPathsRigOptions());
  EXPECT_EQ(one->summary().static_vertices, 194);
  EXPECT_EQ(one->boundary_mode(), BoundaryMode::kFixedVertices);
  // With a target that moves everything, nothing is static and the rig floats.
  auto two = LoadRig("cylinder/cylinder.obj",
                     {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-1_cylinder-1.obj"}, testing::NoPathsRigOptions());
  EXPECT_EQ(two->summary().static_vertices, 0);
  EXPECT_EQ(two->boundary_mode(), BoundaryMode::kAnchored);  // the internal anchor holds it
  RigOptions surface_only = testing::NoPathsRigOptions();
  surface_only.interior = false;
  auto floating = LoadRig("cylinder/cylinder.obj",
                          {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-1_cylinder-1.obj"}, surface_only);
  EXPECT_EQ(floating->boundary_mode(), BoundaryMode::kFloating);
  const auto g = floating->gauge_vertices();
  EXPECT_NE(g[0], g[1]);
  EXPECT_NE(g[1], g[2]);
}

TEST(Rig, UserFixedVerticesAreBoundaryConditions) {
  RigOptions options = testing::NoPathsRigOptions();
  options.fixed_vertices = {5, 100, 399};
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-1.obj"}, options);
  EXPECT_EQ(rig->fixed_vertices(), (std::vector<int>{5, 100, 399}));
  EXPECT_EQ(rig->summary().user_fixed_vertices, 3);
  EXPECT_EQ(rig->boundary_mode(), BoundaryMode::kFixedVertices);

  options.fixed_vertices = {7};
  auto partial = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-1.obj"}, options);
  EXPECT_EQ(partial->boundary_mode(), BoundaryMode::kPartiallyFixed);
}

TEST(Rig, RefusesAFixedVertexOutOfRange) {
  RigOptions options;
  options.fixed_vertices = {3, 420};
  const Error e = CatchError([&] {
    LoadRig("cylinder/cylinder.obj", {"cylinder/poses-1_cylinder-1.obj"}, options);
  });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("fixed_vertices[1] = 420"));
}

TEST(Rig, RefusesATargetWithAnotherVertexCount) {
  const Error e = CatchError([] { LoadRig("cylinder/cylinder.obj", {"cube/poses-1_cube-1.obj"}); });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("poses-1_cube-1.obj"));
  EXPECT_THAT(e.what(), HasSubstr("1538 vertices"));
}

TEST(Rig, RefusesATargetWithOtherFacesNamingTheFace) {
  TriangleMesh rest = LoadMesh(DataPath("cylinder/cylinder.obj"));
  TriangleMesh target = LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj"));
  std::swap(target.faces(321, 0), target.faces(321, 1));
  const Error e = CatchError([&] { Rig::Build(rest, {target}); });
  EXPECT_THAT(e.what(), HasSubstr("poses-2_cylinder-1.obj"));
  EXPECT_THAT(e.what(), HasSubstr("face 321"));
}

TEST(Rig, RefusesDuplicateTargetNames) {
  const Error e = CatchError([] {
    LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj", "cylinder/poses-2_cylinder-1.obj"});
  });
  EXPECT_THAT(e.what(), HasSubstr("used twice"));
}

TEST(Rig, RefusesARigWithoutTargets) {
  const Error e = CatchError([] { LoadRig("cylinder/cylinder.obj", {}); });
  EXPECT_THAT(e.what(), HasSubstr("at least one target"));
}

TEST(Rig, RefusesANonFiniteTargetVertex) {
  TriangleMesh rest = LoadMesh(DataPath("cylinder/cylinder.obj"));
  TriangleMesh target = LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj"));
  target.vertices(211, 0) = std::numeric_limits<double>::infinity();
  const Error e = CatchError([&] { Rig::Build(rest, {target}); });
  EXPECT_THAT(e.what(), HasSubstr("poses-2_cylinder-1.obj"));
  EXPECT_THAT(e.what(), HasSubstr("vertex 211"));
}

TEST(Rig, ReportsDegenerateTriangles) {
  TriangleMesh rest = LoadMesh(DataPath("cylinder/cylinder.obj"));
  TriangleMesh target = LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj"));
  // Collapse face 40 of the target onto a line: a zero-area triangle.
  const int a = target.faces(40, 0), b = target.faces(40, 1), c = target.faces(40, 2);
  target.vertices.row(c) = 0.5 * (target.vertices.row(a) + target.vertices.row(b));
  auto rig = Rig::Build(rest, {target});
  EXPECT_GE(rig->summary().degenerate_faces, 1);
  EXPECT_EQ(rig->summary().first_degenerate_face, std::min(40, rig->summary().first_degenerate_face));
  EXPECT_THAT(rig->summary().notes, ::testing::Contains(HasSubstr("degenerate")));
}

TEST(Rig, RefusesOptionsOutOfRange) {
  RigOptions options;
  options.min_rest_length_fraction = 0.0;
  const Error e = CatchError([&] { LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"}, options); });
  EXPECT_THAT(e.what(), HasSubstr("min_rest_length_fraction"));
}

TEST(HessianPattern, SlotsAddressTheRightEntries) {
  auto rig = LoadRig("cylinder/cylinder.obj", {"cylinder/poses-2_cylinder-1.obj"});
  const auto& p = *rig->internals().pattern;
  const auto& m = p.matrix;
  const int n = rig->num_vertices();
  ASSERT_EQ(m.n, 3 * n);
  auto row_col = [&](int slot) {
    const int col = static_cast<int>(std::upper_bound(m.column_starts.begin(), m.column_starts.end(), slot) -
                                     m.column_starts.begin()) - 1;
    return std::make_pair(m.row_indices[slot], col);
  };
  for (int q = 0; q < rig->num_springs(); ++q) {
    for (int ci = 0; ci < 3; ++ci) {
      for (int cj = 0; cj < 3; ++cj) {
        const auto [r, c] = row_col(p.spring_slots[q][3 * ci + cj]);
        ASSERT_EQ(r, 3 * rig->spring_a()[q] + ci);
        ASSERT_EQ(c, 3 * rig->spring_b()[q] + cj);
      }
    }
  }
  const int rows[6] = {0, 0, 0, 1, 1, 2}, cols[6] = {0, 1, 2, 1, 2, 2};
  for (int v = 0; v < n; ++v) {
    for (int i = 0; i < 6; ++i) {
      const auto [r, c] = row_col(p.vertex_slots[v][i]);
      ASSERT_EQ(r, 3 * v + rows[i]);
      ASSERT_EQ(c, 3 * v + cols[i]);
    }
  }
  // Rows sorted within every column (CHOLMOD's packed, sorted form).
  for (int j = 0; j < m.n; ++j) {
    for (int k = m.column_starts[j] + 1; k < m.column_starts[j + 1]; ++k) {
      ASSERT_LT(m.row_indices[k - 1], m.row_indices[k]);
    }
  }
}

}  // namespace
}  // namespace springblend
