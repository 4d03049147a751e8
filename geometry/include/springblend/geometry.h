// The array types shared by the solver and the client: a triangle mesh as a vertex array and a face array.
// Header-only (Eigen), so a plug-in that only talks to a server needs none of the solver's libraries.
#pragma once

#include <Eigen/Core>
#include <string>

namespace springblend {

using Points = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;  // #V by 3
using Faces = Eigen::Matrix<int, Eigen::Dynamic, 3, Eigen::RowMajor>;     // #F by 3, 0-based

struct TriangleMesh {
  std::string name;    // the target's name (file stem for loaded meshes); used in messages
  std::string source;  // where it came from (a path, or "memory"); used in messages
  Points vertices;
  Faces faces;
  int polygons_split = 0;  // polygons with more than three corners that loading fan-triangulated
};

}  // namespace springblend
