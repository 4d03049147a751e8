// Where the CLI writes solved frames: an OBJ file (one frame), OBJ files DIR/frame_0000.obj ... (many frames),
// or, when the output path ends in .pc2, one PC2 point cache holding every frame (frame = index + 1).
#pragma once

#include <memory>
#include <string>

#include "springblend/geometry.h"
#include "springblend/point_cache.h"

namespace springblend::cli {

class FrameOutput {
 public:
  // many: several frames go to a directory of OBJ files (a PC2 path takes any number). Creates that
  // directory; throws Error (invalid input) naming the path when it cannot write there.
  FrameOutput(std::string out, bool many, Faces faces, int vertices);
  // Frames come in order, 0, 1, 2 ...
  void Write(int index, const Points& positions);
  // Puts the point cache in place (OBJ files are already). Throws Error naming the path.
  void Finish();

 private:
  std::string out_;
  bool many_;
  Faces faces_;
  std::unique_ptr<PointCacheWriter> cache_;
};

}  // namespace springblend::cli
