#include "interior.h"

#include <fmt/format.h>

#include <map>
#include <unordered_map>

#include "springblend/error.h"

namespace springblend::internal {
namespace {

// Boundary loops, each ordered so that the cap triangles (b, a, cap) continue the faces' orientation.
// Throws a plain message if a boundary vertex sits on two loops (a pinch), which a fan cannot close.
std::vector<std::vector<int>> BoundaryLoops(const Faces& faces) {
  std::map<std::pair<int, int>, int> directed;  // directed edge -> count
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    for (int c = 0; c < 3; ++c) ++directed[{faces(f, c), faces(f, (c + 1) % 3)}];
  }
  // A boundary edge a->b has no twin b->a; the cap walks it backwards: b -> a.
  std::unordered_map<int, int> next;
  for (const auto& [edge, count] : directed) {
    if (directed.count({edge.second, edge.first}) != 0) continue;
    if (!next.emplace(edge.second, edge.first).second) {
      throw std::runtime_error(fmt::format("boundary vertex {} is shared by two holes", edge.second));
    }
  }
  std::vector<std::vector<int>> loops;
  while (!next.empty()) {
    std::vector<int> loop;
    const int start = next.begin()->first;
    int v = start;
    do {
      auto it = next.find(v);
      if (it == next.end()) throw std::runtime_error(fmt::format("the hole at vertex {} is not a closed loop", v));
      loop.push_back(v);
      v = it->second;
      next.erase(it);
    } while (v != start);
    loops.push_back(std::move(loop));
  }
  return loops;
}

}  // namespace

Points CapPositions(const Interior& interior, const Points& surface) {
  Points caps(interior.cap_vertices(), 3);
  for (int c = 0; c < interior.cap_vertices(); ++c) {
    Eigen::RowVector3d sum = Eigen::RowVector3d::Zero();
    for (int v : interior.cap_loops[c]) sum += surface.row(v);
    caps.row(c) = sum / static_cast<double>(interior.cap_loops[c].size());
  }
  return caps;
}

Interior BuildInterior(const Points& rest, const Faces& faces, const TetrahedralizeOptions& options) {
  Interior interior;
  interior.surface_vertices = static_cast<int>(rest.rows());
  interior.vertices = rest;
  try {
    interior.cap_loops = BoundaryLoops(faces);
  } catch (const std::runtime_error& e) {
    interior.reason = fmt::format("the surface is open and cannot be capped ({}): surface springs only", e.what());
    interior.cap_loops.clear();
    return interior;
  }
  const Points caps = CapPositions(interior, rest);
  Points closed(rest.rows() + caps.rows(), 3);
  closed << rest, caps;
  Eigen::Index cap_faces = 0;
  for (const auto& loop : interior.cap_loops) cap_faces += static_cast<Eigen::Index>(loop.size());
  Faces closed_faces(faces.rows() + cap_faces, 3);
  closed_faces.topRows(faces.rows()) = faces;
  Eigen::Index f = faces.rows();
  for (int c = 0; c < interior.cap_vertices(); ++c) {
    const auto& loop = interior.cap_loops[c];
    const int cap = interior.surface_vertices + c;
    for (size_t i = 0; i < loop.size(); ++i) {
      // The loop walks each boundary edge against its face's direction, which is the direction the cap's
      // triangle must run along it: (current, next, cap).
      closed_faces.row(f++) << loop[i], loop[(i + 1) % loop.size()], cap;
    }
  }
  try {
    TetMesh tet = Tetrahedralize(closed, closed_faces, options);
    interior.vertices = std::move(tet.vertices);
    interior.tets = std::move(tet.tets);
  } catch (const Error& e) {
    if (e.code() == ErrorCode::kInternal) throw;  // e.g. no TetGen helper installed: not the surface's fault
    interior.reason = fmt::format("{}{}: surface springs only",
                                  interior.cap_loops.empty() ? "" :
                                  fmt::format("after capping {} holes, ", interior.cap_loops.size()),
                                  e.what());
    interior.cap_loops.clear();
    interior.vertices = rest;
    return interior;
  }
  if (interior.cap_loops.empty()) {
    interior.path = Interior::Path::kClosed;
    interior.reason = fmt::format("closed surface tetrahedralized: {} interior vertices, {} tetrahedra",
                                  interior.interior_vertices(), interior.tets.rows());
  } else {
    interior.path = Interior::Path::kCapped;
    interior.reason = fmt::format(
        "open surface: {} holes closed with a vertex at each hole's centre, then tetrahedralized: {} interior "
        "vertices, {} tetrahedra",
        interior.cap_vertices(), interior.interior_vertices(), interior.tets.rows());
  }
  return interior;
}

}  // namespace springblend::internal
