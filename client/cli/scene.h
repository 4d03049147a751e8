// Command-line scene input shared by the local and the remote commands: pins and the JSON frames file.
#pragma once

#include <CLI/CLI.hpp>
#include <string>
#include <utility>
#include <vector>

#include "frame_output.h"
#include "springblend/solve.h"

namespace springblend::cli {

// "VERTEX:x,y,z" -> a pin; throws Error naming the argument.
Pin ParsePin(const std::string& spec);

// Weights as written: one per target in weight order, or by target name (the targets not named get 0).
struct Weights {
  std::vector<double> values;
  std::vector<std::pair<std::string, double>> named;
  bool by_name = false;
};

// --weights items: numbers ("0.5", "0.2") or NAME=NUMBER ("jawOpen=0.7"), not mixed; throws Error naming the
// item.
Weights ParseWeightItems(const std::vector<std::string>& items);

// One weight per target: positional weights as they are (their count is checked with the frame), named ones
// placed by `names` (the character's targets that take weights). An unknown or repeated name is refused,
// naming `where` and the known names.
std::vector<double> ResolveWeights(const Weights& weights, const std::vector<std::string>& names,
                                   const std::string& where);

// The frames file: {"colliders": ["sphere:...", ...],
//                   "frames": [{"weights": [...] or {"NAME": w, ...}, "colliders": [{"translation": [x,y,z],
//                               "rotation": [w,x,y,z]}, ...], "pins": [{"vertex": i, "position": [x,y,z]}]}]}
// Errors name the file and the field (`frames[3].weights.jawOpen`).
struct Scene {
  std::string source;
  std::vector<std::string> colliders;
  std::vector<Frame> frames;             // weights filled by ResolveNames when given by name
  std::vector<Weights> written_weights;  // per frame, as written
  std::vector<int> lines;                // a take's frames: the file line of each (empty for a scene file)
  // Places every frame's named weights by the character's target names (errors name the file and frame).
  void ResolveNames(const std::vector<std::string>& names);
  // Frame i in messages: "frames[3]", or for a take "take.csv line 5".
  std::string FrameName(size_t i) const;
};
Scene LoadScene(const std::string& path);
// The same from memory; source names it in messages.
Scene ParseScene(const std::string& text, const std::string& source);

// Where a command's frames come from: --frames (a JSON scene file, or a take recognised by its header), or --take
// (a captured performance, docs/takes.md) with --map and --lost.
struct FramesInput {
  std::string frames_file;
  std::string take_file;
  std::string map_file;
  std::string lost = "hold";
  bool given() const { return !frames_file.empty() || !take_file.empty(); }
  // Throws Error when --map or --lost came without a take.
  void CheckTakeOptionsUnused() const;
};
void AddFramesOptions(CLI::App* command, FramesInput* input);
// The frames for a character with these target names (weights by name resolved). A take's report goes to stderr
// once; a take's timing becomes a point cache's start frame (at one sample per frame) unless the user gave one.
// Throws Error naming the file (and for a take the line and column) at fault.
Scene LoadFrames(const FramesInput& input, const std::vector<std::string>& names, CacheTiming* timing);

}  // namespace springblend::cli
