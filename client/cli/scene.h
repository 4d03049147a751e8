// Command-line scene input shared by the local and the remote commands: pins and the JSON frames file.
#pragma once

#include <string>
#include <vector>

#include "springblend/solve.h"

namespace springblend::cli {

// "VERTEX:x,y,z" -> a pin; throws Error naming the argument.
Pin ParsePin(const std::string& spec);

// The frames file: {"colliders": ["sphere:...", ...],
//                   "frames": [{"weights": [...], "colliders": [{"translation": [x,y,z],
//                               "rotation": [w,x,y,z]}, ...], "pins": [{"vertex": i, "position": [x,y,z]}]}]}
struct Scene {
  std::vector<std::string> colliders;
  std::vector<Frame> frames;
};
Scene LoadScene(const std::string& path);
// The same from memory; source names it in messages.
Scene ParseScene(const std::string& text, const std::string& source);

}  // namespace springblend::cli
