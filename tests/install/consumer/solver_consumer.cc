// Links springblend::solver from the installed package and loads a mesh: the solver's exported dependencies
// (OpenMesh, CHOLMOD, CGAL, TBB, fmt) resolve.   solver_consumer MESH
#include <springblend/mesh.h>

#include <iostream>

int main(int argc, char** argv) {
  if (argc != 2) return 2;
  const springblend::TriangleMesh mesh = springblend::LoadMesh(argv[1]);
  std::cout << mesh.vertices.rows() << " vertices, diagonal " << springblend::BoundingBoxDiagonal(mesh.vertices)
            << "\n";
  return mesh.vertices.rows() > 0 ? 0 : 1;
}
