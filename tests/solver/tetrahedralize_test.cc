// The guarded TetGen wrapper: the tetrahedralization keeps the surface and fills exactly its volume, and every
// bad input or TetGen failure comes back as an Error while the test process keeps running.
#include "tetrahedralize.h"

#include <Eigen/Geometry>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cmath>
#include <fstream>
#include <functional>
#include <iostream>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "springblend/error.h"
#include "springblend/runtime.h"
#include "tetgen_process.h"

namespace springblend::internal {
namespace {

using ::testing::HasSubstr;

struct Surface {
  Points vertices;
  Faces faces;
};

// Only 'v' and 'f' lines; "f a/b/c" keeps the vertex index a. Keeps the test independent of LoadMesh.
Surface LoadObj(const std::string& path) {
  std::ifstream file(path);
  EXPECT_TRUE(file.good()) << "cannot open " << path;
  std::vector<std::array<double, 3>> points;
  std::vector<std::array<int, 3>> triangles;
  for (std::string line; std::getline(file, line);) {
    std::istringstream fields(line);
    std::string tag;
    fields >> tag;
    if (tag == "v") {
      std::array<double, 3>& p = points.emplace_back();
      fields >> p[0] >> p[1] >> p[2];
    } else if (tag == "f") {
      std::array<int, 3>& t = triangles.emplace_back();
      for (int& corner : t) {
        std::string token;
        fields >> token;
        corner = std::stoi(token.substr(0, token.find('/'))) - 1;
      }
    }
  }
  Surface surface;
  surface.vertices.resize(static_cast<Eigen::Index>(points.size()), 3);
  surface.faces.resize(static_cast<Eigen::Index>(triangles.size()), 3);
  for (size_t i = 0; i < points.size(); ++i) {
    for (int k = 0; k < 3; ++k) surface.vertices(static_cast<Eigen::Index>(i), k) = points[i][k];
  }
  for (size_t i = 0; i < triangles.size(); ++i) {
    for (int k = 0; k < 3; ++k) surface.faces(static_cast<Eigen::Index>(i), k) = triangles[i][k];
  }
  return surface;
}

std::string DataPath(const std::string& relative) { return std::string(SPRINGBLEND_TEST_DATA) + "/" + relative; }

// The box [lo, hi] as 8 vertices and 12 outward-oriented triangles.
Surface Box(const Eigen::RowVector3d& lo, const Eigen::RowVector3d& hi) {
  Surface box;
  box.vertices.resize(8, 3);
  for (int i = 0; i < 8; ++i) {
    box.vertices.row(i) << (i & 1 ? hi.x() : lo.x()), (i & 2 ? hi.y() : lo.y()), (i & 4 ? hi.z() : lo.z());
  }
  box.faces.resize(12, 3);
  box.faces << 0, 2, 1, 1, 2, 3,  // z = lo
      4, 5, 6, 5, 7, 6,           // z = hi
      0, 1, 4, 1, 5, 4,           // y = lo
      2, 6, 3, 3, 6, 7,           // y = hi
      0, 4, 2, 2, 4, 6,           // x = lo
      1, 3, 5, 3, 7, 5;           // x = hi
  return box;
}

Surface UnitCube() { return Box(Eigen::RowVector3d(0, 0, 0), Eigen::RowVector3d(1, 1, 1)); }

// A regular icosahedron of circumradius 1 (outward-oriented).
Surface Icosahedron() {
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  Surface s;
  s.vertices.resize(12, 3);
  s.vertices << -1, t, 0, 1, t, 0, -1, -t, 0, 1, -t, 0, 0, -1, t, 0, 1, t, 0, -1, -t, 0, 1, -t, t, 0, -1, t, 0, 1,
      -t, 0, -1, -t, 0, 1;
  s.vertices /= std::sqrt(1.0 + t * t);
  s.faces.resize(20, 3);
  s.faces << 0, 11, 5, 0, 5, 1, 0, 1, 7, 0, 7, 10, 0, 10, 11, 1, 5, 9, 5, 11, 4, 11, 10, 2, 10, 7, 6, 7, 1, 8, 3, 9,
      4, 3, 4, 2, 3, 2, 6, 3, 6, 8, 3, 8, 9, 4, 9, 5, 2, 4, 11, 6, 2, 10, 8, 6, 7, 9, 8, 1;
  return s;
}

double SixTimesVolume(const Points& v, int a, int b, int c, int d) {
  const Eigen::RowVector3d pa = v.row(a);
  return (v.row(b) - pa).dot((v.row(c) - pa).cross(v.row(d) - pa));
}

double EnclosedVolume(const Surface& s) {
  double sum = 0.0;
  for (int f = 0; f < s.faces.rows(); ++f) {
    sum += s.vertices.row(s.faces(f, 0)).dot(s.vertices.row(s.faces(f, 1)).cross(s.vertices.row(s.faces(f, 2))));
  }
  return sum / 6.0;
}

// Everything Tetrahedralize promises about a result.
void ExpectValidTetMesh(const Surface& s, const TetMesh& mesh) {
  const Eigen::Index n = s.vertices.rows();
  ASSERT_EQ(mesh.surface_vertices, n);
  ASSERT_GE(mesh.vertices.rows(), n);
  ASSERT_GT(mesh.tets.rows(), 0);
  EXPECT_TRUE(mesh.vertices.topRows(n) == s.vertices) << "the surface vertices must come first and unchanged";
  ASSERT_GE(mesh.tets.minCoeff(), 0);
  ASSERT_LT(mesh.tets.maxCoeff(), mesh.vertices.rows());

  double total = 0.0;
  int non_positive = 0;
  std::set<std::array<int, 3>> tet_faces;
  for (Eigen::Index t = 0; t < mesh.tets.rows(); ++t) {
    const auto tet = mesh.tets.row(t);
    const double volume = SixTimesVolume(mesh.vertices, tet[0], tet[1], tet[2], tet[3]) / 6.0;
    non_positive += volume <= 0.0;
    total += volume;
    for (int skip = 0; skip < 4; ++skip) {
      std::array<int, 3> key;
      for (int k = 0, j = 0; k < 4; ++k) {
        if (k != skip) key[j++] = tet[k];
      }
      std::sort(key.begin(), key.end());
      tet_faces.insert(key);
    }
  }
  EXPECT_EQ(non_positive, 0) << "tetrahedra without positive volume";
  const double enclosed = EnclosedVolume(s);
  EXPECT_NEAR(total, enclosed, 1e-9 * std::abs(enclosed));

  int missing = 0;
  for (int f = 0; f < s.faces.rows(); ++f) {
    std::array<int, 3> key{s.faces(f, 0), s.faces(f, 1), s.faces(f, 2)};
    std::sort(key.begin(), key.end());
    missing += tet_faces.count(key) == 0;
  }
  EXPECT_EQ(missing, 0) << "surface triangles that are no face of a tetrahedron";

  const Eigen::RowVector3d lo = s.vertices.colwise().minCoeff(), hi = s.vertices.colwise().maxCoeff();
  for (Eigen::Index v = n; v < mesh.vertices.rows(); ++v) {
    EXPECT_TRUE((mesh.vertices.row(v).array() > lo.array()).all() && (mesh.vertices.row(v).array() < hi.array()).all())
        << "interior vertex " << v << " outside the bounding box";
  }
}

// Runs `call`, which must throw an Error, and returns it.
Error CatchError(const std::function<void()>& call) {
  try {
    call();
  } catch (const Error& error) {
    return error;
  }
  ADD_FAILURE() << "no Error thrown";
  return Error(ErrorCode::kInternal, "no Error thrown");
}

TEST(Tetrahedralize, FillsTheUnitCubeKeepingItsTwelveTriangles) {
  const Surface cube = UnitCube();
  const TetMesh mesh = Tetrahedralize(cube.vertices, cube.faces);
  ExpectValidTetMesh(cube, mesh);
}

TEST(Tetrahedralize, FillsAnIcosahedron) {
  const Surface ball = Icosahedron();
  ExpectValidTetMesh(ball, Tetrahedralize(ball.vertices, ball.faces));
}

TEST(Tetrahedralize, HonoursTheVolumeBoundAndTheSteinerCap) {
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  const TetMesh plain = Tetrahedralize(cube.vertices, cube.faces);
  TetrahedralizeOptions options;
  options.max_volume = 0.25 * EnclosedVolume(cube) / static_cast<double>(plain.tets.rows());
  const TetMesh fine = Tetrahedralize(cube.vertices, cube.faces, options);
  ExpectValidTetMesh(cube, fine);
  EXPECT_GT(fine.vertices.rows(), plain.vertices.rows());
  EXPECT_GT(fine.tets.rows(), 2 * plain.tets.rows());

  options = {};
  options.max_steiner_points = 0;
  const TetMesh bare = Tetrahedralize(cube.vertices, cube.faces, options);
  ExpectValidTetMesh(cube, bare);
  EXPECT_EQ(bare.vertices.rows(), cube.vertices.rows());
}

TEST(Tetrahedralize, FillsTheBundledCube) {
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  ASSERT_EQ(cube.vertices.rows(), 1538);
  const auto start = std::chrono::steady_clock::now();
  const TetMesh mesh = Tetrahedralize(cube.vertices, cube.faces);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::cout << "[ timing   ] cube.obj: " << mesh.vertices.rows() << " vertices (" << mesh.surface_vertices
            << " on the surface), " << mesh.tets.rows() << " tets in " << seconds << " s\n";
  ExpectValidTetMesh(cube, mesh);
}

TEST(Tetrahedralize, RefusesAnOpenSurfaceNamingABoundaryEdge) {
  Surface cube = UnitCube();
  cube.faces.conservativeResize(11, 3);  // drop face 11 = (3, 7, 5)
  const Error error = CatchError([&] { Tetrahedralize(cube.vertices, cube.faces); });
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("3 boundary edges"));
  EXPECT_THAT(error.what(), HasSubstr("edge (3, 5)"));
}

TEST(Tetrahedralize, RefusesASelfIntersectingSurface) {
  // Two closed boxes that overlap, in one face list: closed and manifold, but the faces cross.
  const Surface a = Box(Eigen::RowVector3d(0, 0, 0), Eigen::RowVector3d(1, 1, 1));
  const Surface b = Box(Eigen::RowVector3d(0.5, 0.25, 0.25), Eigen::RowVector3d(1.5, 0.75, 0.75));
  Surface both;
  both.vertices.resize(16, 3);
  both.vertices << a.vertices, b.vertices;
  both.faces.resize(24, 3);
  both.faces << a.faces, (b.faces.array() + 8).matrix();
  const Error error = CatchError([&] { Tetrahedralize(both.vertices, both.faces); });
  std::cout << "[ message  ] " << error.what() << "\n";
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("intersects itself"));
}

TEST(Tetrahedralize, RefusesDegenerateSurfaces) {
  // A tetrahedron's faces on four points in one plane: closed and oriented, but flat.
  Surface flat;
  flat.vertices.resize(4, 3);
  flat.vertices << 0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0;
  flat.faces.resize(4, 3);
  flat.faces << 0, 2, 1, 0, 1, 3, 1, 2, 3, 0, 3, 2;
  Error error = CatchError([&] { Tetrahedralize(flat.vertices, flat.faces); });
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("encloses no volume"));

  Surface extra = UnitCube();
  extra.vertices.conservativeResize(9, 3);
  extra.vertices.row(8) = extra.vertices.row(6);
  error = CatchError([&] { Tetrahedralize(extra.vertices, extra.faces); });
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("vertices 6 and 8 are at the same position"));
  extra.vertices.row(8) << 0.5, 0.5, 0.5;
  error = CatchError([&] { Tetrahedralize(extra.vertices, extra.faces); });
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("unused vertices (in no face): 1, e.g. vertex 8"));

  error = CatchError([&] { Tetrahedralize(flat.vertices.topRows(3), flat.faces.topRows(1)); });
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("at least 4"));

  Surface flipped = UnitCube();
  flipped.faces.row(0) = flipped.faces.row(0).reverse().eval();
  error = CatchError([&] { Tetrahedralize(flipped.vertices, flipped.faces); });
  EXPECT_EQ(error.code(), ErrorCode::kInvalidInput);
  EXPECT_THAT(error.what(), HasSubstr("not consistently oriented"));
}

TEST(Tetrahedralize, RefusesBadOptions) {
  const Surface cube = UnitCube();
  TetrahedralizeOptions options;
  options.radius_edge_ratio = 1.0;
  EXPECT_EQ(CatchError([&] { Tetrahedralize(cube.vertices, cube.faces, options); }).code(), ErrorCode::kInvalidInput);
  options = {};
  options.timeout_seconds = 0.0;
  EXPECT_EQ(CatchError([&] { Tetrahedralize(cube.vertices, cube.faces, options); }).code(), ErrorCode::kInvalidInput);
}

TEST(Tetrahedralize, KillsTetGenAtTheTimeoutAndCarriesOn) {
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  TetrahedralizeOptions options;
  options.timeout_seconds = 0.001;
  const Error error = CatchError([&] { Tetrahedralize(cube.vertices, cube.faces, options); });
  EXPECT_EQ(error.code(), ErrorCode::kNumerical);
  EXPECT_THAT(error.what(), HasSubstr("timed out"));
  // The process is still here and TetGen still works.
  ExpectValidTetMesh(cube, Tetrahedralize(cube.vertices, cube.faces));
}

TEST(Tetrahedralize, RunsFromTwoThreadsAtOnce) {
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  const TetMesh reference = Tetrahedralize(cube.vertices, cube.faces);
  std::array<TetMesh, 2> meshes;
  std::array<std::string, 2> errors;
  std::array<std::thread, 2> threads;
  for (size_t i = 0; i < threads.size(); ++i) {
    threads[i] = std::thread([&, i] {
      try {
        meshes[i] = Tetrahedralize(cube.vertices, cube.faces);
      } catch (const std::exception& error) {
        errors[i] = error.what();
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  for (const std::string& error : errors) EXPECT_EQ(error, "");
  for (const TetMesh& mesh : meshes) {
    EXPECT_TRUE(mesh.vertices == reference.vertices);
    EXPECT_TRUE(mesh.tets == reference.tets);
  }
}

// The helper is a program of ours, found next to the test (build/<preset>/libexec/springblend from tests/), not
// this test binary started again.
TEST(TetGenHelper, IsOurHelperProgram) {
  const std::string helper = tetgen::FindHelper();
  EXPECT_THAT(helper, ::testing::EndsWith("/springblend-tetgen"));
}

TEST(TetGenHelper, AnExplicitPathComesFirstAndAMissingOneSaysWhere) {
  SetTetGenHelper("/nonexistent/springblend-tetgen");
  const Error error = CatchError([] { tetgen::FindHelper(); });
  SetTetGenHelper("");
  EXPECT_EQ(error.code(), ErrorCode::kInternal);
  EXPECT_THAT(error.what(), HasSubstr("/nonexistent/springblend-tetgen"));
  EXPECT_THAT(error.what(), HasSubstr("SPRINGBLEND_TETGEN_HELPER"));
  // Found again once the explicit path is cleared.
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  ExpectValidTetMesh(cube, Tetrahedralize(cube.vertices, cube.faces));
}

// Whether `pid` is gone: reaped, or a zombie nobody reaped yet.
bool Gone(pid_t pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string line;
  if (!std::getline(stat, line)) return true;
  const size_t close = line.rfind(')');
  return close != std::string::npos && close + 2 < line.size() && line[close + 2] == 'Z';
}

// A process that started a helper is killed with SIGKILL (no destructor runs): the helper goes with it.
TEST(TetGenHelper, DiesWithItsParent) {
  // Orphans are re-parented to this process, so the helper can be reaped and its end seen here.
  ASSERT_EQ(prctl(PR_SET_CHILD_SUBREAPER, 1), 0);
  int report[2];
  ASSERT_EQ(pipe(report), 0);
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  const pid_t parent = fork();  // this test runs alone in its process (ctest), so the fork is single-threaded
  ASSERT_GE(parent, 0);
  if (parent == 0) {
    close(report[0]);
    tetgen::HelperProcess helper(cube.vertices, cube.faces, "", tetgen::Task::kHold, 0);
    const pid_t pid = helper.pid();
    if (write(report[1], &pid, sizeof(pid)) != sizeof(pid)) _exit(1);
    for (;;) pause();
  }
  close(report[1]);
  pid_t helper = -1;
  ASSERT_EQ(read(report[0], &helper, sizeof(helper)), static_cast<ssize_t>(sizeof(helper)));
  close(report[0]);
  ASSERT_GT(helper, 0);
  // The helper reads its request and ties itself to the parent; give it the time to get there.
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  ASSERT_FALSE(Gone(helper)) << "the helper ended by itself";
  ASSERT_EQ(kill(parent, SIGKILL), 0);
  int status = 0;
  ASSERT_EQ(waitpid(parent, &status, 0), parent);
  pid_t reaped = 0;
  for (int i = 0; i < 100 && reaped == 0; ++i) {
    reaped = waitpid(helper, &status, WNOHANG);
    if (reaped == 0) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  prctl(PR_SET_CHILD_SUBREAPER, 0);
  if (reaped != helper) {
    kill(helper, SIGKILL);
    FAIL() << "the helper outlived its parent by 5 s";
  }
  ASSERT_TRUE(WIFSIGNALED(status));
  EXPECT_EQ(WTERMSIG(status), SIGKILL);
}

// A helper that burns CPU is stopped by its own RLIMIT_CPU, even with a far deadline in the parent.
TEST(TetGenHelper, HasItsOwnCpuLimit) {
  const Surface cube = LoadObj(DataPath("cube/cube.obj"));
  tetgen::HelperProcess helper(cube.vertices, cube.faces, "", tetgen::Task::kSpin, 1);
  const auto start = tetgen::Clock::now();
  const tetgen::Outcome outcome = helper.Collect(start + std::chrono::seconds(30));
  EXPECT_FALSE(outcome.timed_out);
  EXPECT_LT(tetgen::Clock::now() - start, std::chrono::seconds(10));
  ASSERT_TRUE(outcome.wait_status.has_value());
  ASSERT_TRUE(WIFSIGNALED(*outcome.wait_status));
  EXPECT_THAT(WTERMSIG(*outcome.wait_status), ::testing::AnyOf(SIGXCPU, SIGKILL));
}

TEST(TetGenHelper, CpuLimitFollowsTheTimeout) {
  EXPECT_EQ(tetgen::CpuSecondsFor(0.001), 2);
  EXPECT_EQ(tetgen::CpuSecondsFor(60.0), 61);
  EXPECT_EQ(tetgen::CpuSecondsFor(1e8), 0);  // none
}

}  // namespace
}  // namespace springblend::internal
