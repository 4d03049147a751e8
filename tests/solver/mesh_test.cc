// Loading meshes through OpenMesh in every supported format, and every refusal naming its culprit.
#include "springblend/mesh.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cstdint>
#include <string>
#include <vector>

#include "springblend/error.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CatchError;
using testing::DataPath;
using testing::TempDir;

constexpr char kTetrahedronObj[] =
    "# a tetrahedron\n"
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
    "f 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n";

TEST(LoadMesh, ReadsTheBundledCylinderInFileOrder) {
  const TriangleMesh mesh = LoadMesh(DataPath("cylinder/cylinder.obj"));
  EXPECT_EQ(mesh.vertices.rows(), 420);
  EXPECT_EQ(mesh.faces.rows(), 800);
  EXPECT_EQ(mesh.name, "cylinder");
  // First line of the file: v 2.000000 0.475529 -0.154509
  EXPECT_DOUBLE_EQ(mesh.vertices(0, 0), 2.0);
  EXPECT_NEAR(mesh.vertices(0, 1), 0.475529, 1e-7);
  EXPECT_NEAR(mesh.vertices(0, 2), -0.154509, 1e-7);
}

TEST(LoadMesh, AllFormatsGiveTheSameMesh) {
  TempDir dir;
  const TriangleMesh obj = LoadMesh(dir.Write("t.obj", kTetrahedronObj));
  const TriangleMesh off = LoadMesh(dir.Write(
      "t.off", "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n"));
  const TriangleMesh ply = LoadMesh(dir.Write(
      "t.ply",
      "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
      "element face 4\nproperty list uchar int vertex_indices\nend_header\n"
      "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n"));
  for (const TriangleMesh* m : {&off, &ply}) {
    EXPECT_EQ(m->vertices, obj.vertices);
    EXPECT_EQ(m->faces, obj.faces);
  }
  // STL stores triangles with their own corners; OpenMesh merges equal corners back into vertices.
  const TriangleMesh stl = LoadMesh(dir.Write(
      "t.stl",
      "solid t\n"
      "facet normal 0 0 -1\nouter loop\nvertex 0 0 0\nvertex 0 1 0\nvertex 1 0 0\nendloop\nendfacet\n"
      "facet normal 0 -1 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 0 1\nendloop\nendfacet\n"
      "facet normal 1 1 1\nouter loop\nvertex 1 0 0\nvertex 0 1 0\nvertex 0 0 1\nendloop\nendfacet\n"
      "facet normal -1 0 0\nouter loop\nvertex 0 0 0\nvertex 0 0 1\nvertex 0 1 0\nendloop\nendfacet\n"
      "endsolid t\n"));
  EXPECT_EQ(stl.vertices.rows(), 4);
  EXPECT_EQ(stl.faces.rows(), 4);
}

TEST(LoadMesh, RefusesPlyAndOffHeadersItsReaderWouldTrust) {
  // Fuzzer findings (issue 9): OpenMesh's PLY reader loops forever without end_header and crashes on
  // garbled headers; its binary OFF reader allocates whatever the counts say. Each is now a clear error.
  struct Case {
    std::string file, text, message;
  };
  std::string binary_off = "OFF BINARY\n";
  const std::int32_t counts[3] = {100000000, 100000000, 0};
  binary_off.append(reinterpret_cast<const char*>(counts), sizeof(counts));
  const std::vector<Case> cases = {
      {"a.ply", "ply\nformat ascii 1.0\nelement vertex 4\n", "no end_header"},
      {"b.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty flot x\nend_header\n0 0 0\n",
       "unknown property type 'flot'"},
      {"c.ply", "ply\nformat ascii 1.0\nelement vertex 99999\nproperty float x\nend_header\n0 0 0\n",
       "cannot hold"},
      {"d.ply", "ply\nformat ascii 1.0\nelemnt vertex 4\nend_header\n", "line 3: unexpected 'elemnt'"},
      {"e.ply", "plyx\nend_header\n", "the first line is not 'ply'"},
      // A fuzzer input that hung the reader: a count that is not a number.
      {"i.ply", "ply\nformat ascii 1.0\nelement vertex t face 4\nend_header\n0 0 0\n", "not 'element NAME COUNT'"},
      {"f.off", binary_off, "do not fit"},
      {"g.off", "OFF\n999999999 1 0\n0 0 0\n", "more than the file's"},
      {"h.off", "XOFFY\n", "does not start with OFF"},
  };
  TempDir dir;
  for (const Case& c : cases) {
    try {
      LoadMesh(dir.Write(c.file, c.text));
      ADD_FAILURE() << c.file << " was accepted";
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::kInvalidInput) << c.file;
      EXPECT_THAT(e.what(), HasSubstr(c.message)) << c.file;
      EXPECT_THAT(e.what(), HasSubstr(c.file)) << c.file;
    }
  }
}

TEST(LoadMesh, SplitsPolygonsIntoTriangles) {
  TempDir dir;
  const TriangleMesh quad =
      LoadMesh(dir.Write("q.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"));
  EXPECT_EQ(quad.faces.rows(), 2);
  EXPECT_EQ(quad.polygons_split, 1);
}

TEST(LoadMesh, MissingFileIsNotFound) {
  const Error e = CatchError([] { LoadMesh("/nonexistent/rest.obj"); });
  EXPECT_EQ(e.code(), ErrorCode::kNotFound);
  EXPECT_THAT(e.what(), HasSubstr("/nonexistent/rest.obj"));
}

TEST(LoadMesh, UnsupportedExtensionIsRefused) {
  TempDir dir;
  const std::string path = dir.Write("mesh.fbx", "not a mesh");
  const Error e = CatchError([&] { LoadMesh(path); });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("mesh.fbx"));
  EXPECT_THAT(e.what(), HasSubstr(".fbx"));
}

TEST(LoadMesh, EmptyMeshIsRefused) {
  TempDir dir;
  const std::string path = dir.Write("empty.obj", "# nothing here\n");
  const Error e = CatchError([&] { LoadMesh(path); });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("empty.obj"));
  EXPECT_THAT(e.what(), HasSubstr("no vertices"));
}

TEST(LoadMesh, FacelessMeshIsRefused) {
  TempDir dir;
  const std::string path = dir.Write("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n");
  const Error e = CatchError([&] { LoadMesh(path); });
  EXPECT_THAT(e.what(), HasSubstr("no faces"));
}

TEST(ValidateMesh, NamesTheNonFiniteVertex) {
  TriangleMesh mesh = LoadMesh(DataPath("cylinder/cylinder.obj"));
  mesh.vertices(17, 1) = std::numeric_limits<double>::quiet_NaN();
  const Error e = CatchError([&] { ValidateMesh(mesh); });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("cylinder.obj"));
  EXPECT_THAT(e.what(), HasSubstr("vertex 17"));
  EXPECT_THAT(e.what(), HasSubstr("y coordinate"));

  mesh.vertices(17, 1) = 0.0;
  mesh.vertices(3, 2) = std::numeric_limits<double>::infinity();
  EXPECT_THAT(CatchError([&] { ValidateMesh(mesh); }).what(), HasSubstr("vertex 3"));
}

TEST(ValidateMesh, NamesTheFaceWithAnIndexOutOfRange) {
  TriangleMesh mesh = LoadMesh(DataPath("cylinder/cylinder.obj"));
  mesh.faces(250, 2) = 420;
  const Error e = CatchError([&] { ValidateMesh(mesh); });
  EXPECT_THAT(e.what(), HasSubstr("face 250"));
  EXPECT_THAT(e.what(), HasSubstr("vertex 420"));
  mesh.faces(250, 2) = -3;
  EXPECT_THAT(CatchError([&] { ValidateMesh(mesh); }).what(), HasSubstr("face 250"));
}

TEST(ValidateMesh, NamesTheFaceThatRepeatsAVertex) {
  TriangleMesh mesh = LoadMesh(DataPath("cylinder/cylinder.obj"));
  mesh.faces(9, 1) = mesh.faces(9, 0);
  const Error e = CatchError([&] { ValidateMesh(mesh); });
  EXPECT_THAT(e.what(), HasSubstr("face 9 repeats a vertex"));
}

TEST(LoadMesh, OutOfRangeIndexInAFileIsRefused) {
  TempDir dir;
  const std::string path = dir.Write("bad.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n");
  const Error e = CatchError([&] { LoadMesh(path); });
  EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(e.what(), HasSubstr("bad.obj"));
}

// OpenMesh's OBJ reader parses coordinates as float32, so a round trip keeps about seven digits: far
// below every tolerance the solver is held to (1e-6 of the diagonal) and the float32 wire format.
TEST(WriteObj, RoundTripsAtFloatPrecision) {
  TempDir dir;
  const TriangleMesh mesh = LoadMesh(DataPath("cube/cube.obj"));
  Points moved = mesh.vertices * (1.0 / 3.0);
  WriteObj(dir.File("out.obj"), moved, mesh.faces);
  const TriangleMesh back = LoadMesh(dir.File("out.obj"));
  EXPECT_EQ(back.faces, mesh.faces);
  EXPECT_LT(testing::MaxDistance(back.vertices, moved), 1e-7 * BoundingBoxDiagonal(moved));
}

}  // namespace
}  // namespace springblend
