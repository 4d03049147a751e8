// Tetrahedralize: the checks before TetGen runs, the switches, and what its helper's answer means. TetGen itself
// runs in the helper process (tetgen_helper.cc), started and read by tetgen_process.cc.
#include "tetrahedralize.h"

#include <Eigen/Geometry>
#include <fmt/format.h>
#include <sys/wait.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <optional>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "springblend/error.h"
#include "tetgen_process.h"

namespace springblend::internal {
namespace {

using tetgen::Clock;
using tetgen::MessageKind;
using Triangle = std::array<int, 3>;

// Why a surface cannot be tetrahedralized; `what` completes "cannot tetrahedralize the surface: ".
struct Failure {
  ErrorCode code;
  std::string what;
};

Error ToError(const Failure& failure) {
  return Error(failure.code, "cannot tetrahedralize the surface: " + failure.what);
}

[[noreturn]] void Refuse(const std::string& what) { throw ToError({ErrorCode::kInvalidInput, what}); }

Failure TetGenFailed(const std::string& what) { return {ErrorCode::kNumerical, "TetGen " + what}; }

// ---------------------------------------------------------------------------------------------------------
// Checks in the caller's process, before TetGen sees the surface.

void CheckOptions(const TetrahedralizeOptions& options) {
  const auto refuse = [](const std::string& what) {
    throw Error(ErrorCode::kInvalidInput, "TetrahedralizeOptions: " + what);
  };
  if (!(options.radius_edge_ratio > 1.0) || !std::isfinite(options.radius_edge_ratio)) {
    refuse(fmt::format("radius_edge_ratio must be a finite number > 1 (got {})", options.radius_edge_ratio));
  }
  if (!std::isfinite(options.max_volume)) refuse(fmt::format("max_volume must be finite (got {})", options.max_volume));
  if (!(options.timeout_seconds > 0.0) || !std::isfinite(options.timeout_seconds)) {
    refuse(fmt::format("timeout_seconds must be a finite number > 0 (got {})", options.timeout_seconds));
  }
}

// One side of a face: the edge (lo, hi) with lo < hi, and whether the face runs along it from lo to hi.
struct HalfEdge {
  int lo, hi, face;
  bool forward;
};

// Every edge must join exactly two faces that run along it in opposite directions.
void CheckClosedManifoldOriented(const Faces& faces) {
  std::vector<HalfEdge> half_edges;
  half_edges.reserve(3 * static_cast<size_t>(faces.rows()));
  for (int f = 0; f < faces.rows(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const int a = faces(f, k), b = faces(f, (k + 1) % 3);
      half_edges.push_back({std::min(a, b), std::max(a, b), f, a < b});
    }
  }
  std::sort(half_edges.begin(), half_edges.end(),
            [](const HalfEdge& x, const HalfEdge& y) { return std::tie(x.lo, x.hi) < std::tie(y.lo, y.hi); });

  std::optional<HalfEdge> boundary, non_manifold, misoriented;
  int boundary_count = 0, non_manifold_count = 0, misoriented_count = 0, non_manifold_faces = 0;
  for (size_t begin = 0, end = 0; begin < half_edges.size(); begin = end) {
    while (end < half_edges.size() && half_edges[end].lo == half_edges[begin].lo &&
           half_edges[end].hi == half_edges[begin].hi) {
      ++end;
    }
    const HalfEdge& e = half_edges[begin];
    if (end - begin == 1) {
      if (boundary_count++ == 0) boundary = e;
    } else if (end - begin > 2) {
      if (non_manifold_count++ == 0) {
        non_manifold = e;
        non_manifold_faces = static_cast<int>(end - begin);
      }
    } else if (e.forward == half_edges[begin + 1].forward) {
      if (misoriented_count++ == 0) misoriented = e;
    }
  }
  const auto plural = [](int count) { return count == 1 ? "" : "s"; };
  if (boundary) {
    Refuse(fmt::format("it is not closed: {} boundary edge{} (used by one face only), e.g. edge ({}, {}) of face {}",
                       boundary_count, plural(boundary_count), boundary->lo, boundary->hi, boundary->face));
  }
  if (non_manifold) {
    Refuse(fmt::format("it is not manifold: {} edge{} shared by more than two faces, e.g. edge ({}, {}) by {} faces",
                       non_manifold_count, plural(non_manifold_count), non_manifold->lo, non_manifold->hi,
                       non_manifold_faces));
  }
  if (misoriented) {
    Refuse(fmt::format("its faces are not consistently oriented: {} edge{} where both faces run the same way, "
                       "e.g. edge ({}, {})",
                       misoriented_count, plural(misoriented_count), misoriented->lo, misoriented->hi));
  }
}

// Six times the volume enclosed by a closed, consistently oriented surface (divergence theorem).
double SixTimesEnclosedVolume(const Points& vertices, const Faces& faces) {
  double sum = 0.0;
  for (int f = 0; f < faces.rows(); ++f) {
    const Eigen::Vector3d a = vertices.row(faces(f, 0)), b = vertices.row(faces(f, 1)), c = vertices.row(faces(f, 2));
    sum += a.dot(b.cross(c));
  }
  return sum;
}

void CheckSurface(const Points& vertices, const Faces& faces) {
  const Eigen::Index n = vertices.rows();
  if (n < 4) Refuse(fmt::format("it has {} vertices; a closed surface needs at least 4", n));
  if (faces.rows() < 4) Refuse(fmt::format("it has {} faces; a closed surface needs at least 4", faces.rows()));
  for (Eigen::Index v = 0; v < n; ++v) {
    if (!vertices.row(v).allFinite()) Refuse(fmt::format("vertex {} has a non-finite coordinate", v));
  }
  std::vector<char> used(static_cast<size_t>(n), 0);
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const int v = faces(f, k);
      if (v < 0 || v >= n) Refuse(fmt::format("face {} refers to vertex {}, out of range [0, {})", f, v, n));
      used[static_cast<size_t>(v)] = 1;
    }
    if (faces(f, 0) == faces(f, 1) || faces(f, 1) == faces(f, 2) || faces(f, 0) == faces(f, 2)) {
      Refuse(fmt::format("face {} repeats a vertex", f));
    }
  }
  // TetGen would merge coinciding vertices (or, with -M, fail on them) and renumber the rest.
  std::vector<int> order(static_cast<size_t>(n));
  std::iota(order.begin(), order.end(), 0);
  const auto position = [&](int v) { return std::tie(vertices(v, 0), vertices(v, 1), vertices(v, 2)); };
  std::sort(order.begin(), order.end(), [&](int a, int b) { return position(a) < position(b); });
  for (size_t i = 1; i < order.size(); ++i) {
    if (position(order[i - 1]) == position(order[i])) {
      Refuse(fmt::format("vertices {} and {} are at the same position", std::min(order[i - 1], order[i]),
                         std::max(order[i - 1], order[i])));
    }
  }
  if (const auto unused = std::find(used.begin(), used.end(), 0); unused != used.end()) {
    Refuse(fmt::format("it has unused vertices (in no face): {}, e.g. vertex {}",
                       std::count(used.begin(), used.end(), 0), unused - used.begin()));
  }
  CheckClosedManifoldOriented(faces);
  const double diagonal = (vertices.colwise().maxCoeff() - vertices.colwise().minCoeff()).norm();
  if (std::abs(SixTimesEnclosedVolume(vertices, faces)) <= 1e-12 * std::pow(diagonal, 3)) {
    Refuse("it encloses no volume (are all its vertices in one plane?)");
  }
}

std::string SignalName(int signal_number) {
  const char* abbreviation = sigabbrev_np(signal_number);
  return abbreviation != nullptr ? fmt::format("SIG{}", abbreviation) : fmt::format("signal {}", signal_number);
}

// Why a run that ended in time delivered no mesh.
Failure DescribeFailure(const tetgen::Outcome& run) {
  if (!run.complete) {
    if (!run.wait_status) return TetGenFailed("ended without a result");
    if (WIFSIGNALED(*run.wait_status)) return TetGenFailed("crashed with " + SignalName(WTERMSIG(*run.wait_status)));
    return TetGenFailed(fmt::format("exited with code {} without a result", WEXITSTATUS(*run.wait_status)));
  }
  switch (run.header.kind) {
    case MessageKind::kTetGenError:
      // The codes of TetGen 1.5's terminatetetgen(). 3 to 5 and 10 are about the input.
      switch (run.header.error_code) {
        case 1:
          return TetGenFailed("ran out of memory (error 1)");
        case 2:
          return TetGenFailed("had an internal error (error 2)");
        case 3:
          return {ErrorCode::kInvalidInput, "TetGen found a self-intersection (error 3)"};
        case 4:
          return {ErrorCode::kInvalidInput,
                  "TetGen found features below its tolerance, e.g. a vertex almost on a face it does not belong to "
                  "(error 4)"};
        case 5:
          return {ErrorCode::kInvalidInput, "TetGen found two almost coincident faces (error 5)"};
        case 10:
          return {ErrorCode::kInvalidInput, "TetGen rejected the input (error 10)"};
        default:
          return TetGenFailed(fmt::format("stopped with error {}", run.header.error_code));
      }
    case MessageKind::kOutOfMemory:
      return TetGenFailed("ran out of memory");
    case MessageKind::kUnknownException:
      return TetGenFailed("threw an unexpected exception");
    case MessageKind::kMesh:
    case MessageKind::kIntersections:
      break;
  }
  return {ErrorCode::kInternal, "TetGen's process sent an unexpected message"};
}

// ---------------------------------------------------------------------------------------------------------
// Input, and reading and checking the result.

TetMesh ReadMesh(const tetgen::Outcome& run, int surface_vertices) {
  TetMesh mesh;
  mesh.surface_vertices = surface_vertices;
  mesh.vertices.resize(run.header.points, 3);
  mesh.tets.resize(run.header.count, 4);
  const size_t point_bytes = sizeof(double) * static_cast<size_t>(mesh.vertices.size());
  std::memcpy(mesh.vertices.data(), run.payload.data(), point_bytes);
  std::memcpy(mesh.tets.data(), run.payload.data() + point_bytes, sizeof(int) * static_cast<size_t>(mesh.tets.size()));
  return mesh;
}

double SixTimesVolume(const Points& v, int a, int b, int c, int d) {
  const Eigen::RowVector3d pa = v.row(a);
  return (v.row(b) - pa).dot((v.row(c) - pa).cross(v.row(d) - pa));
}

// TetGen's tets all have one orientation; makes it the positive one.
std::optional<Failure> OrientPositively(TetMesh* mesh) {
  Eigen::Index positive = 0, negative = 0;
  for (Eigen::Index t = 0; t < mesh->tets.rows(); ++t) {
    const auto tet = mesh->tets.row(t);
    const double volume = SixTimesVolume(mesh->vertices, tet[0], tet[1], tet[2], tet[3]);
    positive += volume > 0.0;
    negative += volume < 0.0;
  }
  const Eigen::Index count = mesh->tets.rows();
  if (negative == count) {
    const Eigen::VectorXi first = mesh->tets.col(0);
    mesh->tets.col(0) = mesh->tets.col(1);
    mesh->tets.col(1) = first;
  } else if (positive != count) {
    return TetGenFailed(fmt::format("returned {} tetrahedra of mixed orientation ({} positive, {} negative, {} flat)",
                                    count, positive, negative, count - positive - negative));
  }
  return std::nullopt;
}

// Every input face must be a face of exactly one tet (the one inside).
std::optional<Failure> CheckSurfaceKept(const Faces& faces, const TetMesh& mesh) {
  std::vector<std::pair<Triangle, int>> surface;
  surface.reserve(static_cast<size_t>(faces.rows()));
  for (int f = 0; f < faces.rows(); ++f) {
    Triangle key{faces(f, 0), faces(f, 1), faces(f, 2)};
    std::sort(key.begin(), key.end());
    surface.emplace_back(key, f);
  }
  std::sort(surface.begin(), surface.end());
  std::vector<int> hits(static_cast<size_t>(faces.rows()), 0);
  for (Eigen::Index t = 0; t < mesh.tets.rows(); ++t) {
    for (int skip = 0; skip < 4; ++skip) {
      Triangle key;
      for (int k = 0, j = 0; k < 4; ++k) {
        if (k != skip) key[j++] = mesh.tets(t, k);
      }
      if (std::max({key[0], key[1], key[2]}) >= mesh.surface_vertices) continue;
      std::sort(key.begin(), key.end());
      const auto found = std::lower_bound(surface.begin(), surface.end(), std::make_pair(key, -1));
      if (found != surface.end() && found->first == key) ++hits[static_cast<size_t>(found->second)];
    }
  }
  for (size_t f = 0; f < hits.size(); ++f) {
    if (hits[f] != 1) {
      return TetGenFailed(
          fmt::format("did not keep the surface: input face {} is a face of {} tetrahedra, not 1", f, hits[f]));
    }
  }
  return std::nullopt;
}

// The contract of Tetrahedralize: surface vertices first and unchanged, valid indices, positive volumes, every
// surface triangle kept.
std::optional<Failure> CheckAndOrient(const Points& vertices, const Faces& faces, TetMesh* mesh) {
  const Eigen::Index n = vertices.rows();
  if (mesh->vertices.rows() < n) {
    return TetGenFailed(
        fmt::format("returned {} vertices, fewer than the {} of the surface", mesh->vertices.rows(), n));
  }
  for (Eigen::Index v = 0; v < n; ++v) {
    if (mesh->vertices.row(v) != vertices.row(v)) {
      return TetGenFailed(fmt::format("moved or renumbered the surface vertices (vertex {} differs)", v));
    }
  }
  if (mesh->tets.rows() == 0) return TetGenFailed("returned no tetrahedra");
  if ((mesh->tets.array() < 0).any() || (mesh->tets.array() >= mesh->vertices.rows()).any()) {
    return TetGenFailed("returned a tetrahedron with a vertex index out of range");
  }
  if (auto failure = OrientPositively(mesh)) return failure;
  return CheckSurfaceKept(faces, *mesh);
}

std::string MeshingSwitches(const TetrahedralizeOptions& options) {
  // p: the input is a surface; Y: no Steiner points on it; M: no merging of coplanar neighbouring faces or of
  // close vertices (either would change the input triangles); q: the quality bound (TetGen reads it without an
  // exponent); Q: quiet.
  std::string switches = fmt::format("pYMq{:.6f}", options.radius_edge_ratio);
  if (options.max_volume > 0.0) switches += fmt::format("a{:.17g}", options.max_volume);
  if (options.max_steiner_points >= 0) switches += fmt::format("S{}", options.max_steiner_points);
  return switches + "Q";
}

}  // namespace

TetMesh Tetrahedralize(const Points& vertices, const Faces& faces, const TetrahedralizeOptions& options) {
  CheckOptions(options);
  CheckSurface(vertices, faces);
  // Far-off deadlines are capped so that the time arithmetic cannot overflow.
  const auto timeout = std::chrono::duration<double>(std::min(options.timeout_seconds, 1e8));
  const Clock::time_point deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(timeout);

  const std::int64_t cpu_seconds = tetgen::CpuSecondsFor(options.timeout_seconds);
  const tetgen::Outcome run =
      tetgen::HelperProcess(vertices, faces, MeshingSwitches(options), tetgen::Task::kMesh, cpu_seconds)
          .Collect(deadline);
  if (run.timed_out) {
    throw ToError(TetGenFailed(fmt::format(
        "timed out: no result within {} s (timeout_seconds), its process was killed", options.timeout_seconds)));
  }
  std::optional<Failure> failure;
  if (run.complete && run.header.kind == MessageKind::kMesh) {
    TetMesh mesh = ReadMesh(run, static_cast<int>(vertices.rows()));
    failure = CheckAndOrient(vertices, faces, &mesh);
    if (!failure) return mesh;
  } else {
    failure = DescribeFailure(run);
  }
  // The checks before the run cannot see self-intersections, the usual reason why TetGen fails on a closed
  // surface. Its -d check finds them; it gets what is left of the time.
  const tetgen::Outcome diagnosis =
      tetgen::HelperProcess(vertices, faces, "pd", tetgen::Task::kDiagnose, cpu_seconds).Collect(deadline);
  if (diagnosis.complete && diagnosis.header.kind == MessageKind::kIntersections && diagnosis.header.count > 0) {
    std::array<std::int32_t, 2> example;
    std::memcpy(example.data(), diagnosis.payload.data(), sizeof(example));
    Refuse(fmt::format("it intersects itself ({} pairs of faces, e.g. faces {} and {}); {}", diagnosis.header.count,
                       example[0], example[1], failure->what));
  }
  throw ToError(*failure);
}

}  // namespace springblend::internal
