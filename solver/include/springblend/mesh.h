// Triangle meshes as the solver sees them: a vertex array and a face array, in the order of the file.
#pragma once

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

// Parse a mesh from memory; format is "obj", "ply", "off" or "stl"; source names it in messages.
TriangleMesh LoadMeshFromText(const std::string& text, const std::string& format, const std::string& source);

// Write an OBJ file (v and f lines only) with positions at full double precision.
void WriteObj(const std::string& path, const Points& vertices, const Faces& faces);

// Checks a single mesh: not empty, every face index in range, no repeated corner, finite coordinates.
// Throws Error naming the source and the vertex or face at fault.
void ValidateMesh(const TriangleMesh& mesh);

// Axis-aligned bounding box diagonal length.
double BoundingBoxDiagonal(const Points& vertices);

}  // namespace springblend
