// The rig's volume (paper section 3.1): a constrained Delaunay tetrahedralization of the rest surface, with
// open boundaries closed by caps first, or an explicit surface-only fallback that says why.
#pragma once

#include <string>
#include <vector>

#include "springblend/mesh.h"
#include "tetrahedralize.h"

namespace springblend::internal {

using Tets = Eigen::Matrix<int, Eigen::Dynamic, 4, Eigen::RowMajor>;

struct Interior {
  enum class Path { kClosed, kCapped, kSurfaceOnly };
  Path path = Path::kSurfaceOnly;
  std::string reason;  // why the path was taken, in words
  // Each cap vertex (ids surface_vertices, surface_vertices + 1, ...) sits at the centroid of its loop of
  // boundary vertices, in every shape.
  std::vector<std::vector<int>> cap_loops;
  // All vertices in the rest shape: surface, then cap vertices, then interior (Steiner) vertices.
  Points vertices;
  Tets tets;
  int surface_vertices = 0;
  int cap_vertices() const { return static_cast<int>(cap_loops.size()); }
  int interior_vertices() const {
    return static_cast<int>(vertices.rows()) - surface_vertices - cap_vertices();
  }
};

// Closes every boundary loop with a fan around a new centroid vertex and tetrahedralizes. Never throws for
// a surface TetGen cannot take: the result is then kSurfaceOnly with TetGen's (or the capping's) reason.
Interior BuildInterior(const Points& rest, const Faces& faces, const TetrahedralizeOptions& options);

// Positions of the cap vertices for the surface positions `surface` (centroids of their loops).
Points CapPositions(const Interior& interior, const Points& surface);

}  // namespace springblend::internal
