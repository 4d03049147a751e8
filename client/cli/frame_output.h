// Where the CLI writes solved frames: an OBJ file (one frame), OBJ files DIR/frame_0000.obj ... (many frames),
// or, when the output path ends in .pc2, one PC2 point cache holding every frame (sample i at frame
// start_frame + i * sample_rate: a shot starting at frame 1001 lines up with its animation).
#pragma once

#include <memory>
#include <string>

#include <CLI/CLI.hpp>

#include "springblend/geometry.h"
#include "springblend/point_cache.h"

namespace springblend::cli {

// Where a point cache's samples sit on the timeline: --start-frame and --sample-rate (frames per sample).
struct CacheTiming {
  double start_frame = 1.0;
  double sample_rate = 1.0;
  bool given = false;  // either option was given (then the output must be a .pc2)
};
// Adds --start-frame and --sample-rate to a command that writes frames.
void AddCacheTimingOptions(CLI::App* command, CacheTiming* timing);

class FrameOutput {
 public:
  // many: several frames go to a directory of OBJ files (a PC2 path takes any number). Creates that
  // directory; throws Error (invalid input) naming the path when it cannot write there, or when timing was
  // given for an output that is not a point cache.
  FrameOutput(std::string out, bool many, Faces faces, int vertices, const CacheTiming& timing = {});
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
