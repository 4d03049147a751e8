// Constrained Delaunay tetrahedralization of a closed triangle surface with TetGen 1.5, run in a helper process
// (springblend-tetgen, see tetgen_process.h) so that TetGen's exit(), thrown error codes, crashes and endless
// loops cannot take the caller down.
#pragma once

#include <Eigen/Core>

#include "springblend/mesh.h"

namespace springblend::internal {

struct TetrahedralizeOptions {
  double radius_edge_ratio = 2.0;  // TetGen -q quality bound (radius-edge ratio), > 1.0
  double max_volume = -1.0;        // -a bound on tet volume (absolute units); <= 0: none
  int max_steiner_points = -1;     // -S cap; < 0: none
  double timeout_seconds = 60.0;   // the guarded child is killed after this (shared with the -d check after a failure)
};

struct TetMesh {
  // First rows = the input surface vertices, in the same order and unchanged; then interior (Steiner) vertices.
  Points vertices;
  Eigen::Matrix<int, Eigen::Dynamic, 4, Eigen::RowMajor> tets;  // 0-based indices into vertices, positive volume
  int surface_vertices = 0;
};

// Tetrahedralizes the volume bounded by a closed, manifold, consistently oriented triangle surface with
// TetGen's switches "pYMq<ratio>" (+ "a<max_volume>", "S<max_steiner_points>"): the surface comes back as it
// went in (no Steiner points on it, every input triangle is a face of exactly one tet); interior Steiner points
// are allowed. Throws Error:
//   kInvalidInput  options out of range, or a surface TetGen cannot take: too few vertices, an open boundary or
//                  a non-manifold edge, inconsistent orientation, coinciding or unused vertices, no enclosed
//                  volume, self-intersections (found by TetGen's -d check after a failed run);
//   kNumerical     TetGen failed (internal error, out of memory, crash) or timed out, or its result broke the
//                  contract above.
// Safe to call from several threads at once; the calling process never crashes, exits or hangs because of TetGen.
TetMesh Tetrahedralize(const Points& vertices, const Faces& faces, const TetrahedralizeOptions& options = {});

}  // namespace springblend::internal
