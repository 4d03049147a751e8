// Loading meshes in every supported format (OBJ, PLY and STL through OpenMesh, OFF through our own reader), and
// every refusal naming its culprit.
#include "springblend/mesh.h"

#include <OpenMesh/Core/IO/IOManager.hh>
#include <OpenMesh/Core/IO/importer/ImporterT.hh>
#include <OpenMesh/Core/Mesh/PolyMesh_ArrayKernelT.hh>
#include <fmt/format.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdint>
#include <fstream>
#include <future>
#include <sstream>
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

// Writes `text` to dir/file and expects LoadMesh to refuse it as invalid input, with a message that starts with
// the file's path and contains every one of `parts`.
void ExpectRefused(const TempDir& dir, const std::string& file, const std::string& text,
                   const std::vector<std::string>& parts) {
  try {
    LoadMesh(dir.Write(file, text));
    ADD_FAILURE() << file << " was accepted";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidInput) << file;
    EXPECT_THAT(e.what(), ::testing::StartsWith(dir.File(file) + ": ")) << file;
    for (const auto& part : parts) EXPECT_THAT(e.what(), HasSubstr(part)) << file;
  }
}

TEST(LoadMesh, RefusesPlyAndOffHeadersItsReaderWouldTrust) {
  // Fuzzer findings (issue 9): OpenMesh's PLY reader loops forever without end_header and crashes on
  // garbled headers; its binary OFF reader allocates whatever the counts say. Each is now a clear error (OFF
  // through our own reader, which refuses binary OFF outright).
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
      // A fuzzer input that hung the reader: a version that is not a number.
      {"j.ply", "ply\nformat ascii \xbf\xa6VVndices\nelement vertex 1\nproperty float x\nend_header\n0\n",
       "line 2: not 'format ascii|binary_little_endian|binary_big_endian VERSION'"},
      // The header ends at an end_header line, not at those letters in a comment (the reader would read on to the
      // end of the file and loop there).
      {"k.ply", "ply\nformat ascii 1.0\ncomment end_header\nelement vertex 1\nproperty float x\n0\n",
       "no end_header line"},
      {"l.ply", "ply\ncomment made by hand\nformat ascii 1.0\nend_header\n", "line 2: the format line must come first"},
      {"f.off", binary_off, "binary OFF is not supported"},
      {"g.off", "OFF\n999999999 1 0\n0 0 0\n", "more than the file's"},
      {"h.off", "XOFFY\n", "does not start with OFF"},
  };
  TempDir dir;
  for (const Case& c : cases) ExpectRefused(dir, c.file, c.text, {c.message});
}

TEST(LoadMesh, PlyObjInfoLinesAreReadAsComments) {
  // OpenMesh reads an obj_info line's words as header keywords: here its end_header would end the header early.
  TempDir dir;
  const TriangleMesh reference = LoadMesh(dir.Write("t.obj", kTetrahedronObj));
  const TriangleMesh ply = LoadMesh(dir.Write(
      "t.ply",
      "ply\nformat ascii 1.0\nobj_info exported before end_header\nelement vertex 4\nproperty float x\n"
      "property float y\nproperty float z\nelement face 4\nproperty list uchar int vertex_indices\n"
      "  obj_info element face 99999999999\nend_header\n"
      "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n"));
  EXPECT_EQ(ply.vertices, reference.vertices);
  EXPECT_EQ(ply.faces, reference.faces);
}

// OpenMesh's OFF reader, as the loader used it before OFF had a reader of its own: the raw vertices and
// polygons it reports, for comparing the two on files both read.
struct OpenMeshSoup {
  std::vector<std::array<double, 3>> points;
  std::vector<std::vector<int>> polygons;
};

OpenMeshSoup ReadOffWithOpenMesh(const std::string& text) {
  struct Traits : OpenMesh::DefaultTraits {
    using Point = OpenMesh::Vec3d;
  };
  using Mesh = OpenMesh::PolyMesh_ArrayKernelT<Traits>;
  class Recorder final : public OpenMesh::IO::ImporterT<Mesh> {
   public:
    Recorder(Mesh& mesh, OpenMeshSoup& soup) : ImporterT<Mesh>(mesh), soup_(soup) {}
    OpenMesh::VertexHandle add_vertex(const OpenMesh::Vec3f& p) override {
      soup_.points.push_back({p[0], p[1], p[2]});
      return ImporterT<Mesh>::add_vertex(p);
    }
    OpenMesh::FaceHandle add_face(const VHandles& corners) override {
      std::vector<int> polygon;
      for (const auto& vh : corners) polygon.push_back(vh.idx());
      soup_.polygons.push_back(polygon);
      return ImporterT<Mesh>::add_face(corners);
    }

   private:
    OpenMeshSoup& soup_;
  };
  OpenMeshSoup soup;
  Mesh mesh;
  Recorder recorder(mesh, soup);
  OpenMesh::IO::Options options;
  std::istringstream in(text);
  EXPECT_TRUE(OpenMesh::IO::IOManager().read(in, "off", recorder, options));
  return soup;
}

// An OBJ file's v and f lines as OFF (the coordinates' text kept as written), with an optional per-vertex
// suffix (normals, colours) after the keyword's prefix.
std::string ObjAsOff(const std::string& obj_path, const std::string& keyword = "OFF",
                     const std::string& vertex_suffix = "") {
  std::ifstream in(obj_path);
  std::vector<std::string> vertices, faces;
  for (std::string line; std::getline(in, line);) {
    std::istringstream words(line);
    std::string kind;
    words >> kind;
    if (kind == "v") {
      std::string x, y, z;
      words >> x >> y >> z;
      vertices.push_back(x + " " + y + " " + z + vertex_suffix);
    } else if (kind == "f") {
      std::string face, corner;
      int corners = 0;
      while (words >> corner) {
        face += fmt::format(" {}", std::stoi(corner.substr(0, corner.find('/'))) - 1);
        ++corners;
      }
      faces.push_back(std::to_string(corners) + face);
    }
  }
  std::string off = fmt::format("{}\n{} {} 0\n", keyword, vertices.size(), faces.size());
  for (const auto& v : vertices) off += v + "\n";
  for (const auto& f : faces) off += f + "\n";
  return off;
}

// A strip of quads and a pentagon, at coordinates float32 cannot hold exactly.
constexpr char kPolygonsObj[] =
    "v 0.1 0 0\nv 1.1 0 0\nv 2.1 0 0\nv 0.1 1.3 0\nv 1.1 1.3 0.7\nv 2.1 1.3 0\nv 1.1 2.9 0.2\n"
    "f 1 2 5 4\nf 2 3 6 5\nf 4 5 6 7 1\n";
constexpr char kPolygonsOff[] =
    "OFF\n7 3 0\n0.1 0 0\n1.1 0 0\n2.1 0 0\n0.1 1.3 0\n1.1 1.3 0.7\n2.1 1.3 0\n1.1 2.9 0.2\n"
    "4 0 1 4 3\n4 1 2 5 4\n5 3 4 5 6 0\n";

TEST(LoadMesh, OffGivesWhatOpenMeshsOffReaderAndTheObjFileGive) {
  TempDir dir;
  struct Case {
    std::string name, off, obj_path;
  };
  const std::vector<Case> cases = {
      {"cylinder.off", ObjAsOff(DataPath("cylinder/cylinder.obj")), DataPath("cylinder/cylinder.obj")},
      {"spot.off", ObjAsOff(DataPath("spot/spot_low_resolution.obj")), DataPath("spot/spot_low_resolution.obj")},
      // Vertex colours and normals are read past, as OpenMesh does.
      {"colours.off", ObjAsOff(DataPath("cylinder/cylinder.obj"), "COFF", " 0.5 0.25 1.0 1.0"),
       DataPath("cylinder/cylinder.obj")},
      {"normals.off", ObjAsOff(DataPath("cylinder/cylinder.obj"), "NOFF", " 0 0 1"), DataPath("cylinder/cylinder.obj")},
      {"both.off", ObjAsOff(DataPath("cylinder/cylinder.obj"), "CNOFF", " 0 0 1 255 128 0"),
       DataPath("cylinder/cylinder.obj")},
      {"polygons.off", kPolygonsOff, dir.Write("polygons.obj", kPolygonsObj)},
  };
  for (const Case& c : cases) {
    const TriangleMesh off = LoadMesh(dir.Write(c.name, c.off));
    const TriangleMesh obj = LoadMesh(c.obj_path);
    EXPECT_EQ(off.vertices, obj.vertices) << c.name;
    EXPECT_EQ(off.faces, obj.faces) << c.name;
    EXPECT_EQ(off.polygons_split, obj.polygons_split) << c.name;
    // And the same vertices and fan triangles as OpenMesh's OFF reader gave before.
    const OpenMeshSoup reference = ReadOffWithOpenMesh(c.off);
    ASSERT_EQ(static_cast<size_t>(off.vertices.rows()), reference.points.size()) << c.name;
    for (size_t v = 0; v < reference.points.size(); ++v) {
      for (int k = 0; k < 3; ++k) {
        ASSERT_EQ(off.vertices(static_cast<Eigen::Index>(v), k), reference.points[v][k]) << c.name << " vertex " << v;
      }
    }
    Eigen::Index f = 0;
    for (const auto& polygon : reference.polygons) {
      for (size_t k = 1; k + 1 < polygon.size(); ++k, ++f) {
        ASSERT_LT(f, off.faces.rows()) << c.name;
        EXPECT_EQ(off.faces.row(f), Eigen::RowVector3i(polygon[0], polygon[k], polygon[k + 1])) << c.name;
      }
    }
    EXPECT_EQ(f, off.faces.rows()) << c.name;
  }
  const TriangleMesh polygons = LoadMesh(dir.File("polygons.off"));
  EXPECT_EQ(polygons.faces.rows(), 2 + 2 + 3);
  EXPECT_EQ(polygons.polygons_split, 3);
  EXPECT_NE(polygons.vertices(0, 0), 0.1) << "rounded to float32, as OpenMesh's readers do";
  EXPECT_EQ(polygons.vertices(0, 0), static_cast<double>(0.1f));
}

TEST(LoadMesh, OffCommentsCountsOnTheKeywordLineAndFaceColoursAreRead) {
  TempDir dir;
  const TriangleMesh reference = LoadMesh(dir.Write("t.obj", kTetrahedronObj));
  const std::string tetrahedron =
      "# a tetrahedron\n"
      "OFF 4 4 6   # counts on the keyword's line\n"
      "\n"
      "0 0 0\n1 0 0  # the x axis\n0 1 0\n\t0 0 1\r\n"
      "# faces: an RGB colour, a colour map index, RGBA, none\n"
      "3 0 2 1 255 0 0\n3 0 1 3 7\n3 1 2 3 0.5 0.5 0.5 1\n3 0 3 2\n"
      "# the end\n";
  const TriangleMesh off = LoadMesh(dir.Write("t.off", tetrahedron));
  EXPECT_EQ(off.vertices, reference.vertices);
  EXPECT_EQ(off.faces, reference.faces);
  // Counts without the edge count, colours on COFF vertices with alpha, a byte order mark.
  const TriangleMesh coff = LoadMesh(dir.Write(
      "c.off", "\xEF\xBB\xBF" "COFF\n4 4\n0 0 0 1 0 0 1\n1 0 0 0 1 0 1\n0 1 0 0 0 1 1\n0 0 1 1 1 1 1\n"
               "3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n"));
  EXPECT_EQ(coff.vertices, reference.vertices);
  EXPECT_EQ(coff.faces, reference.faces);
}

TEST(LoadMesh, OffRefusalsNameTheFileTheLineAndTheFault) {
  struct Case {
    std::string file, text;
    std::vector<std::string> message;
  };
  const std::string vertices = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n";
  const std::string faces = "3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n";
  std::string finding = "OFF 0 0\r";  // the fuzzer's input that made OpenMesh's reader allocate 8 GB
  finding += std::string(1, '\0') + "F 0 0\r" + std::string(1, '\0') + "F 0 0\r\n";
  const std::vector<Case> cases = {
      {"empty.off", "# nothing\n\n", {"does not start with OFF", "empty"}},
      {"keyword.off", "OFFICE\n4 4 0\n", {"line 1:", "does not start with OFF", "'OFFICE'"}},
      {"garbled.off", std::string("\x01OFF\n", 5), {"line 1:", "'\\x01OFF'"}},
      {"binary.off", "OFF BINARY\n\x04\x00\x00\x00", {"line 1:", "binary OFF is not supported"}},
      {"4d.off", "4OFF\n1 0 0\n0 0 0 1\n", {"line 1:", "only 3D vertices"}},
      {"finding.off", finding, {"line 1:", "expected the counts"}},
      {"nocounts.off", "OFF\n# no counts\n", {"line 1:", "counts 'VERTICES FACES EDGES' are missing"}},
      {"negative.off", "OFF\n-4 4 0\n" + vertices + faces, {"line 2:", "expected the counts", "'-4 4 0'"}},
      {"huge.off", "OFF\n4 2000000000 0\n" + vertices + faces,
       {"line 2:", "4 vertices and 2000000000 faces are more than the file's 8 remaining lines"}},
      {"overflow.off", "OFF\n4 99999999999 0\n" + vertices + faces, {"line 2:", "expected the counts"}},
      {"short.off", "OFF\n5 4 0\n" + vertices + faces, {"line 2:", "more than the file's 8 remaining lines"}},
      {"vertex.off", "OFF\n4 4 0\n0 0 0\n1 0\n0 1 0\n0 0 1\n" + faces, {"line 4:", "vertex 1 has 2 numbers", "'x y z'"}},
      {"colour.off", "OFF\n4 4 0\n0 0 0 1 1 1\n1 0 0\n0 1 0\n0 0 1\n" + faces, {"line 3:", "vertex 0 has 6 numbers"}},
      {"coff.off", "COFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n" + faces,
       {"line 3:", "vertex 0 has 3 numbers, but COFF vertices are 'x y z r g b [a]'"}},
      {"word.off", "OFF\n4 4 0\n0 0 0\n1 0 0\n0 one 0\n0 0 1\n" + faces, {"line 5:", "vertex 2: 'one' is not a number"}},
      {"nan.off", "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 nan 1\n" + faces,
       {"line 6:", "vertex 3 has a non-finite y coordinate"}},
      {"range.off", "OFF\n4 4 0\n0 0 0\n1e39 0 0\n0 1 0\n0 0 1\n" + faces, {"line 4:", "'1e39' is not a number"}},
      {"two.off", "OFF\n4 4 0\n" + vertices + "3 0 2 1\n2 0 1\n3 1 2 3\n3 0 3 2\n", {"line 8:", "face 1 has 2 corners"}},
      {"few.off", "OFF\n4 4 0\n" + vertices + "3 0 2 1\n3 0 1 3\n4 1 2 3\n3 0 3 2\n",
       {"line 9:", "face 2 has 4 corners but lists 3 vertex indices"}},
      {"corners.off", "OFF\n4 4 0\n" + vertices + "3 0 2 1\n3 0 1 3\n1000000000 1 2 3\n3 0 3 2\n",
       {"line 9:", "face 2 has 1000000000 corners but lists 3"}},
      {"index.off", "OFF\n4 4 0\n" + vertices + "3 0 2 1\n3 0 1 3\n3 1 2 4\n3 0 3 2\n",
       {"line 9:", "face 2 refers to vertex 4, but the file has 4 vertices"}},
      {"minus.off", "OFF\n4 4 0\n" + vertices + "3 0 2 1\n3 0 -1 3\n3 1 2 3\n3 0 3 2\n",
       {"line 8:", "face 1: '-1' is not a vertex index"}},
      {"facecolour.off", "OFF\n4 4 0\n" + vertices + "3 0 2 1\n3 0 1 3 0.5 0.5\n3 1 2 3\n3 0 3 2\n",
       {"line 8:", "face 1 has 3 corners and 2 more numbers"}},
      {"trailing.off", "OFF\n4 4 0\n" + vertices + faces + "3 0 1 2\n",
       {"line 11:", "data after the last face (4 faces and 4 vertices, as the counts on line 2 say)"}},
  };
  TempDir dir;
  for (const Case& c : cases) ExpectRefused(dir, c.file, c.text, c.message);
}

TEST(LoadMesh, ObjFaceCornersMustNameAVertex) {
  // Fuzzer finding: a corner without a vertex index failed an assertion in OpenMesh's OBJ reader (an abort: the
  // server parses OBJ mesh colliders from requests).
  const std::string v = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n";
  TempDir dir;
  ExpectRefused(dir, "finding.obj", v + "vt 0 0\nf /2 3 1\n", {"line 6:", "face corner '/2' is not V, V/VT"});
  ExpectRefused(dir, "word.obj", v + "f 1 2 3\nf x/1 2 3\n", {"line 6:", "corner 'x/1'"});
  ExpectRefused(dir, "four.obj", v + "f 1 2 3/1/1/1\n", {"line 5:", "corner '3/1/1/1'"});
  ExpectRefused(dir, "huge.obj", v + "f 1 2 99999999999\n", {"line 5:", "corner '99999999999'"});
  ExpectRefused(dir, "slash.obj", v + "f 1 2 /\n", {"line 5:", "corner '/'"});
  // Every corner form OBJ has still reads as before.
  const TriangleMesh plain = LoadMesh(dir.Write("plain.obj", v + "f 1 3 2\nf 1 2 4\n"));
  for (const std::string faces : {"f 1/1 3/1 2/1\nf 1/1 2/1 4/1\n", "f 1//1 3//1 2//1\nf 1//1 2//1 4//1\n",
                                  "f 1/1/1 3/1/1 2/1/1\nf +1 +2 +4\n", "f -4 -2 -3\nf 1/ 2/ 4//\n"}) {
    const TriangleMesh mesh = LoadMesh(dir.Write("forms.obj", v + "vt 0 0\nvn 0 0 1\n" + faces));
    EXPECT_EQ(mesh.faces, plain.faces) << faces;
    EXPECT_EQ(mesh.vertices, plain.vertices) << faces;
  }
}

TEST(LoadMesh, ObjMaterialLibrariesAreNeverOpened) {
  // OpenMesh's OBJ reader opens the file an `mtllib` line names, on the machine that parses it (`mtllib
  // /dev/zero` allocated until the fuzzer stopped it). A FIFO tells: opening it blocks until a writer comes.
  TempDir dir;
  const std::string fifo = dir.File("materials.mtl");
  ASSERT_EQ(mkfifo(fifo.c_str(), 0600), 0);
  const std::string obj = std::string("mtllib ") + fifo + "\nusemtl skin\n" + kTetrahedronObj;
  auto load = std::async(std::launch::async, [&] { return LoadMeshFromText(obj, "obj", "collider.obj"); });
  if (load.wait_for(std::chrono::seconds(5)) != std::future_status::ready) {
    ADD_FAILURE() << "the loader opened the material library " << fifo;
    const int writer = open(fifo.c_str(), O_WRONLY | O_NONBLOCK);  // lets it read an empty file and go on
    if (writer >= 0) close(writer);
  }
  const TriangleMesh mesh = load.get();
  const TriangleMesh reference = LoadMeshFromText(kTetrahedronObj, "obj", "tetrahedron");
  EXPECT_EQ(mesh.faces, reference.faces);
  EXPECT_EQ(mesh.vertices, reference.vertices);
  // Lines keep their numbers with the library line blanked.
  EXPECT_THAT(CatchError([&] { LoadMeshFromText("mtllib " + fifo + "\nv 0 0 0\nf /1 1 1\n", "obj", "c.obj"); }).what(),
              HasSubstr("c.obj: line 3: face corner '/1'"));
}

TEST(LoadMesh, ObjVertexLinesThatDoNotParseAreRefusedNamingTheLine) {
  const std::string faces = "f 1 2 3\n";
  for (const std::string bad : {"v nan 0 0", "v 1,5 0 0", "v 1e400 0 0", "v 1 0", "v 1.0.0 0 0", "v inf 0 0"}) {
    const std::string text = "v 0 0 0\nv 1 0 0\n" + bad + "\nv 0 1 0\n" + faces;
    EXPECT_THAT(CatchError([&] { LoadMeshFromText(text, "obj", "c.obj"); }).what(), HasSubstr("c.obj: line 3"))
        << bad;
  }
  // Comments, a w coordinate, vertex colours and a leading + still read.
  const TriangleMesh ok = LoadMeshFromText("v 0 0 0 # origin\nv +1 0 0 1\nv 0 1 0 0.5 0.5 0.5\n" + faces, "obj", "c.obj");
  EXPECT_EQ(ok.vertices.rows(), 3);
  EXPECT_EQ(ok.vertices(1, 0), 1.0);
}

TEST(LoadMesh, ObjTextLimitsAreCheckedBeforeOpenMesh) {
  std::string fan = "v 0 0 0\n";
  for (int i = 0; i < 50; ++i) fan += fmt::format("v {} {} 1\n", std::cos(i * 0.1), std::sin(i * 0.1));
  for (int i = 0; i < 49; ++i) fan += fmt::format("f 1 {} {}\n", i + 2, i + 3);
  MeshTextLimits limits;
  limits.max_valence = 10;
  EXPECT_THAT(CatchError([&] { LoadMeshFromText(fan, "obj", "c.obj", limits); }).what(), HasSubstr("valence"));
  limits = {};
  limits.max_vertices = 20;
  EXPECT_THAT(CatchError([&] { LoadMeshFromText(fan, "obj", "c.obj", limits); }).what(), HasSubstr("more than 20 vertices"));
  limits = {};
  limits.max_faces = 20;
  EXPECT_THAT(CatchError([&] { LoadMeshFromText(fan, "obj", "c.obj", limits); }).what(), HasSubstr("more than 20 triangles"));
  limits = {};
  limits.max_corners_per_face = 8;
  std::string polygon = fan + "f";
  for (int i = 2; i < 40; ++i) polygon += fmt::format(" {}", i);
  EXPECT_THAT(CatchError([&] { LoadMeshFromText(polygon + "\n", "obj", "c.obj", limits); }).what(),
              HasSubstr("more than 8 corners"));
  EXPECT_EQ(LoadMeshFromText(fan, "obj", "c.obj").faces.rows(), 49);
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
