// Triangle meshes as the solver sees them: a vertex array and a face array, in the order of the file.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "springblend/geometry.h"

namespace springblend {

// Points, Faces and TriangleMesh live in springblend/geometry.h (header-only, shared with the client).

// Load OBJ, PLY, OFF or STL (by extension), keeping the file's vertex order exactly; polygons are
// fan-triangulated. OBJ, PLY and STL go through OpenMesh (OBJ face corners and PLY headers are checked first, OBJ
// material libraries never opened), ASCII OFF through a strict reader of our own (binary OFF is refused). Throws
// Error naming the file and the offending element (and the line, for OFF and OBJ face corners).
TriangleMesh LoadMesh(const std::string& path);

// Caps checked on OBJ text in one linear pass before OpenMesh sees it (OpenMesh's cost grows with vertex valence
// faster than linearly, so a small file can cost minutes). 0 turns a cap off.
struct MeshTextLimits {
  std::int64_t max_vertices = 0;
  std::int64_t max_faces = 0;            // triangles after fan triangulation
  std::int64_t max_corners_per_face = 0;
  std::int64_t max_valence = 0;          // face corners on one vertex
};

// Parse a mesh from memory; format is "obj", "ply", "off" or "stl"; source names it in messages. `limits` apply to
// OBJ text (the format the server takes).
TriangleMesh LoadMeshFromText(const std::string& text, const std::string& format, const std::string& source,
                              const MeshTextLimits& limits = {});

// Write an OBJ file (v and f lines only) with positions at full double precision.
void WriteObj(const std::string& path, const Points& vertices, const Faces& faces);

// Checks a single mesh: not empty, every face index in range, no repeated corner, finite coordinates.
// Throws Error naming the source and the vertex or face at fault.
void ValidateMesh(const TriangleMesh& mesh);

// Axis-aligned bounding box diagonal length.
double BoundingBoxDiagonal(const Points& vertices);

}  // namespace springblend
