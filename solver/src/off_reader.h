// A strict reader for ASCII OFF meshes. OpenMesh 9.0's OFF reader trusts the counts in its header (a garbled
// header made it allocate 8 GB), so OFF files are read here instead: counts are checked against the lines that
// follow before anything is allocated, and every refusal names the file, the line and what is wrong.
#pragma once

#include <array>
#include <string>
#include <string_view>
#include <vector>

namespace springblend {

// Vertices and polygons exactly as a file lists them, before triangulation.
struct PolygonSoup {
  std::vector<std::array<double, 3>> points;  // #V positions, in file order
  std::vector<std::vector<int>> polygons;     // #F corner lists, 0-based, in file order
};

// Reads ASCII OFF: an optional [ST][C][N]OFF keyword line, then "VERTICES FACES [EDGES]" (on the keyword's line
// or the next), one vertex per line (x y z, then nx ny nz with N, r g b [a] with C, s t with ST; only x y z
// are kept) and one face per line (the corner count, that many 0-based indices, then an optional colour of 1,
// 3 or 4 numbers). '#' starts a comment anywhere; blank lines are skipped. Coordinates are rounded to float32,
// as OpenMesh's readers do, so an OFF file gives the same vertices as the same mesh in OBJ.
// Throws Error(kInvalidInput) "SOURCE: line N: ..." for binary OFF, 4D or nD vertices, missing or
// impossible counts, malformed numbers, faces with fewer than three corners, indices out of range, and data
// after the last face.
PolygonSoup ReadOff(std::string_view text, const std::string& source);

}  // namespace springblend
